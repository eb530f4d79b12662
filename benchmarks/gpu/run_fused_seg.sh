#!/usr/bin/env bash
# GPU machine, Note [Fused upsample + argmax] (the linear seg head's Triton kernel):
#   tests    its gpu tests (kernel vs float64 at 1080p, the head choosing it, compiled into a CUDA graph, its speed)
#   sweep    the kernel's time for each block size and warp count (upsample_argmax_kernel.py blocks)
#   cands    the kernels' time searching every class vs each cell's candidates (upsample_argmax_kernel.py candidates)
#   floor    the depth + seg floor with the PyTorch path and with the fused kernel, alternating, on one machine
#   profile  where one frame's time goes (profile_steps.py) with the fused kernel, with the device trace
#   e5       E5 (10,000 frames at 30 Hz, depth + seg + det) with the fused kernel
#   suite    every gpu test (tests/gpu)
source benchmarks/gpu/setup.sh
for part in "$@"; do
case "$part" in
tests)
  timeout 300 python3 -m pytest -m gpu -q -s -p no:cacheprovider tests/gpu/test_upsample_argmax_cuda.py \
    > "$OUT/fused_seg_tests.log" 2>&1
  grep "classes\|seg head\|passed\|failed\|Error" "$OUT/fused_seg_tests.log" | tail -12
  ;;
sweep)
  timeout 120 python3 benchmarks/gpu/upsample_argmax_kernel.py blocks > "$OUT/upsample_argmax_sweep.log" 2>&1
  tail -n 2 "$OUT/upsample_argmax_sweep.log"
  ;;
cands)
  timeout 120 python3 benchmarks/gpu/upsample_argmax_kernel.py candidates 2>&1 | grep -v "WARNING" | tail -n 5
  ;;
floor)
  floor 150 depth,seg floor_fused_depth_seg_torch_a --seg-upsample torch
  floor 150 depth,seg floor_fused_depth_seg_a
  floor 150 depth,seg floor_fused_depth_seg_torch_b --seg-upsample torch
  floor 150 depth,seg floor_fused_depth_seg_b
  ;;
floor1)
  floor 150 depth,seg floor_fused_candidates_depth_seg
  ;;
floor_det)
  floor 200 depth,seg,det floor_fused_depth_seg_det
  ;;
profile)
  TAG=_fused VARIANTS="slot" timeout 200 python3 benchmarks/gpu/profile_steps.py 2>&1 | grep -v "RANDOM\|WARNING" \
    > "$OUT/profile_steps_fused.log"
  grep "mean" "$OUT/profile_steps_fused.log"
  [ -f "$OUT/profile_steps_trace.json.gz" ] && mv "$OUT/profile_steps_trace.json.gz" "$OUT/profile_steps_trace_fused.json.gz"
  ;;
e5)
  timeout 500 python3 -m vpengine.cli.main bench paper --experiments E5 --e5-frames "${E5_FRAMES:-10000}" \
    --det-head frcnn_dinov2_lite --backend compile --tag e5_fused --out "$OUT" 2>&1 | grep -v "RANDOM\|WARNING" | tail -4
  ;;
suite)
  timeout 450 python3 -m pytest -m gpu tests/gpu -q -p no:cacheprovider > "$OUT/gpu_tests_fused.log" 2>&1
  tail -n 3 "$OUT/gpu_tests_fused.log"
  ;;
esac
done
ls "$OUT"
