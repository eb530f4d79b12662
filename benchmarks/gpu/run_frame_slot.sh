#!/usr/bin/env bash
# GPU machine: frame-slot tests on CUDA; the depth + seg floor (compiled, borrowed results) with frames submitted and
# written in place (Engine.frame_slot); where one frame's time goes in thread mode (profile_steps.py).
source benchmarks/gpu/setup.sh
VPENGINE_TEST_DEVICE=cuda timeout 150 python3 -m pytest -q -p no:cacheprovider tests/unit/test_frame_slot.py \
  > "$OUT/frame_slot_tests_on_cuda.log" 2>&1; tail -2 "$OUT/frame_slot_tests_on_cuda.log"
timeout 200 python3 -m vpengine.cli.main bench paper --experiments floor --floor-heads depth,seg --backend compile \
  --frames 100 --results borrow --tag floor_slot_depth_seg_borrow --out "$OUT" 2>&1 | grep "floor:\|Error" | tail -2
TAG=${TAG:-} timeout 200 python3 benchmarks/gpu/profile_steps.py 2>&1 | grep -v "RANDOM\|WARNING" \
  | tee "$OUT/profile_steps${TAG:-}.log" | head -150
ls "$OUT"
