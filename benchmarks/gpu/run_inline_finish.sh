#!/usr/bin/env bash
# GPU machine, Note [Inline finish] (the thread waiting for a frame waits for a head's device work and publishes its
# output itself, instead of being woken by the head's thread):
#   tests    the inline-finish, inline-launch and borrowed-results integration tests on CUDA, and the device-sync
#            and stream-priority gpu tests
#   floor    the depth + seg floor (compiled, borrowed), same machine: heads' threads publish (never), the waiting
#            thread does (auto), and auto with a 200 us driver spin
#   profile  where one frame's time goes (profile_steps.py, frame slot), with inline finish, sleeping and spinning
#   suite    every gpu test (tests/gpu)
source benchmarks/gpu/setup.sh
for part in "$@"; do
case "$part" in
tests)
  VPENGINE_TEST_DEVICE=cuda timeout 200 python3 -m pytest -q -p no:cacheprovider tests/integration/test_inline_finish.py \
    tests/integration/test_inline_launch.py tests/integration/test_borrowed_results.py \
    > "$OUT/inline_finish_tests_on_cuda.log" 2>&1
  tail -n 3 "$OUT/inline_finish_tests_on_cuda.log"
  timeout 200 python3 -m pytest -m gpu -q -p no:cacheprovider tests/gpu/test_engine_gpu.py \
    -k "spinning_device_sync or stream_priority" > "$OUT/inline_finish_gpu_tests.log" 2>&1
  tail -n 3 "$OUT/inline_finish_gpu_tests.log"
  ;;
floor)
  floor 150 depth,seg floor_inline_finish_depth_seg_never --inline-finish never
  floor 150 depth,seg floor_inline_finish_depth_seg_auto
  floor 150 depth,seg floor_inline_finish_depth_seg_auto_spin200 --sync-spin-us 200
  ;;
profile)
  TAG=_inline_finish VARIANTS="slot,slot+spin200" timeout 200 python3 benchmarks/gpu/profile_steps.py \
    2>&1 | grep -v "RANDOM\|WARNING" > "$OUT/profile_steps_inline_finish.log"; grep "mean" "$OUT/profile_steps_inline_finish.log"
  ;;
suite)
  timeout 450 python3 -m pytest -m gpu tests/gpu -q -p no:cacheprovider > "$OUT/gpu_tests_inline_finish.log" 2>&1
  tail -n 3 "$OUT/gpu_tests_inline_finish.log"
  ;;
esac
done
ls "$OUT"
