#!/usr/bin/env bash
# GPU machine, runtime.wait_spin_us (the caller's wait for a frame's results polls its predicted end, Note [Device
# sync]) on top of the inline launch (Note [Inline launch]):
#   profile  where one frame's time goes in thread mode: sleeping waits, the workers' sync spin, the caller's wait
#            spin, both (profile_steps.py)
#   floor    the depth + seg floor (compiled, borrowed): sleeping waits; sync spin 200 us + wait spin 200 us
#   tests    every gpu test (tests/gpu), then the wait-spin, inline-launch and device-sync tests on CUDA
source benchmarks/gpu/setup.sh
case "${1:-all}" in
all|profile)
  TAG=_wait VARIANTS="slot+spin200,slot+wait200,slot+spin200+wait200,slot+spin200+wait100" timeout 300 \
    python3 benchmarks/gpu/profile_steps.py 2>&1 | grep -v "RANDOM\|WARNING" > "$OUT/profile_steps_wait.log"
  grep "mean\|slot-bound" "$OUT/profile_steps_wait.log"
  ;;&
all|floor)
  floor 150 depth,seg floor_wait_depth_seg_borrow_spin0
  floor 150 depth,seg floor_wait_depth_seg_borrow_spin200_wait200 --sync-spin-us 200 --wait-spin-us 200
  ;;
tests)
  timeout 380 python3 -m pytest -m gpu tests/gpu -q -p no:cacheprovider > "$OUT/gpu_tests_wait_spin.log" 2>&1
  tail -n 3 "$OUT/gpu_tests_wait_spin.log"
  VPENGINE_TEST_DEVICE=cuda timeout 180 python3 -m pytest -q -p no:cacheprovider tests/integration/test_wait_spin.py \
    tests/integration/test_inline_launch.py tests/unit/test_device_sync.py > "$OUT/wait_spin_tests_on_cuda.log" 2>&1
  tail -n 3 "$OUT/wait_spin_tests_on_cuda.log"
  ;;
esac
ls "$OUT"
