#!/usr/bin/env bash
# GPU machine, Note [Device sync] with the spin in the driver (runtime.sync_spin_us > 0: sleep through the predicted
# part of the work, then a default-flag CUDA event's synchronize, which polls without the interpreter lock):
#   tests    the device-sync and stream-priority gpu tests
#   floor    the depth + seg floor (compiled, borrowed): sleeping sync, then a 200 us spin window, same machine
#   profile  where one frame's time goes (profile_steps.py): depth + seg and eight depth heads, with and without
#   suite    every gpu test (tests/gpu)
source benchmarks/gpu/setup.sh
for part in "$@"; do
case "$part" in
tests)
  timeout 200 python3 -m pytest -m gpu -q -p no:cacheprovider tests/gpu/test_engine_gpu.py \
    -k "spinning_device_sync or stream_priority" > "$OUT/driver_spin_tests.log" 2>&1
  tail -n 3 "$OUT/driver_spin_tests.log"
  ;;
floor)
  floor 150 depth,seg floor_driver_spin_depth_seg_spin0
  floor 150 depth,seg floor_driver_spin_depth_seg_spin200 --sync-spin-us 200
  ;;
profile)
  TAG=_driver_spin VARIANTS="slot,slot+spin200,slot+fullspin" timeout 200 python3 benchmarks/gpu/profile_steps.py \
    2>&1 | grep -v "RANDOM\|WARNING" > "$OUT/profile_steps_driver_spin.log"; grep "mean" "$OUT/profile_steps_driver_spin.log"
  TAG=_driver_spin_depth8 HEADS=depth:8 VARIANTS="slot,slot+spin200" timeout 200 python3 benchmarks/gpu/profile_steps.py \
    2>&1 | grep -v "RANDOM\|WARNING" > "$OUT/profile_steps_driver_spin_depth8.log"
  grep "mean" "$OUT/profile_steps_driver_spin_depth8.log"
  ;;
suite)
  timeout 450 python3 -m pytest -m gpu tests/gpu -q -p no:cacheprovider > "$OUT/gpu_tests_driver_spin.log" 2>&1
  tail -n 3 "$OUT/gpu_tests_driver_spin.log"
  ;;
esac
done
ls "$OUT"
