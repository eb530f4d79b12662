#!/usr/bin/env bash
# GPU machine, Note [Launch path] (stream and inference mode entered once per worker loop; borrowed results' array
# interfaces cached):
#   profile  cold launch costs (profile_wakeups.py), then where one frame's time goes in thread mode
#            (profile_steps.py: worker launch, inline launch, sync spin 200 us)
#   floor    the depth + seg floor (compiled, borrowed): sleeping sync, sync spin 200 us
#   tests    every gpu test (tests/gpu), then the inline-launch and borrowed-results tests on CUDA
source benchmarks/gpu/setup.sh
case "${1:-all}" in
all|profile)
  timeout 150 python3 benchmarks/gpu/profile_wakeups.py > "$OUT/profile_wakeups.log" 2>&1; tail -n 12 "$OUT/profile_wakeups.log"
  TAG=_launch_path VARIANTS="slot worker launch,slot,slot+spin200" timeout 300 python3 benchmarks/gpu/profile_steps.py \
    2>&1 | grep -v "RANDOM\|WARNING" > "$OUT/profile_steps_launch_path.log"; grep "mean" "$OUT/profile_steps_launch_path.log"
  ;;&
all|floor)
  floor 150 depth,seg floor_launch_path_depth_seg_borrow_spin0
  floor 150 depth,seg floor_launch_path_depth_seg_borrow_spin200 --sync-spin-us 200
  ;;
tests)
  timeout 380 python3 -m pytest -m gpu tests/gpu -q -p no:cacheprovider > "$OUT/gpu_tests_launch_path.log" 2>&1
  tail -n 3 "$OUT/gpu_tests_launch_path.log"
  VPENGINE_TEST_DEVICE=cuda timeout 180 python3 -m pytest -q -p no:cacheprovider tests/integration/test_inline_launch.py \
    tests/integration/test_borrowed_results.py > "$OUT/launch_path_tests_on_cuda.log" 2>&1
  tail -n 3 "$OUT/launch_path_tests_on_cuda.log"
  ;;
esac
ls "$OUT"
