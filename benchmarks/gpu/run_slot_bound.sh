#!/usr/bin/env bash
# GPU machine, after slot-bound runs and the polling device sync:
#   tests   the slot-bound, device-sync and frame-slot tests on CUDA, the compiled engine test; then profile
#   profile where one frame's time goes in thread mode (profile_steps.py, variants: unbound, sync spin, full spin,
#           switch interval)
#   floor   the depth + seg floor (compiled, borrowed), sleeping sync and sync spin 200 us
#   floor3  the floor with the eager detection head too, and depth + seg again, sync spin 200 us
source benchmarks/gpu/setup.sh
case "${1:-tests}" in
tests|gputests)
  VPENGINE_TEST_DEVICE=cuda timeout 420 python3 -m pytest -q -p no:cacheprovider -m "gpu or not gpu" \
    tests/gpu/test_compile_cuda.py::test_slot_bound_runs_read_and_write_the_slots_they_are_told \
    tests/gpu/test_compile_cuda.py::test_a_slot_that_cannot_be_bound_leaves_the_executor_running_unbound \
    tests/gpu/test_compile_cuda.py::test_engine_with_compiled_models_on_cuda_matches_eager \
    tests/gpu/test_engine_gpu.py::test_polling_device_sync_returns_when_the_work_is_done_and_mostly_sleeps \
    tests/unit/test_frame_slot.py tests/unit/test_slot_bound.py tests/unit/test_device_sync.py \
    > "$OUT/slot_bound_tests_on_cuda.log" 2>&1; tail -3 "$OUT/slot_bound_tests_on_cuda.log"
  ;;&
tests|profile)
  TAG=_bound timeout 170 python3 benchmarks/gpu/profile_steps.py 2>&1 | grep -v "RANDOM\|WARNING" \
    > "$OUT/profile_steps_bound.log"; grep "mean\|slot-bound" "$OUT/profile_steps_bound.log"
  ;;
floor)
  VPENGINE_TEST_DEVICE=cuda timeout 100 python3 -m pytest -q -p no:cacheprovider -m "gpu or not gpu" \
    tests/unit/test_slot_bound.py \
    tests/unit/test_device_sync.py \
    tests/gpu/test_engine_gpu.py::test_polling_device_sync_returns_when_the_work_is_done_and_mostly_sleeps \
    > "$OUT/slot_bound_tests_on_cuda_rerun.log" 2>&1; tail -2 "$OUT/slot_bound_tests_on_cuda_rerun.log"
  for spin in 0 200; do
    floor 280 depth,seg floor_bound_depth_seg_borrow_spin$spin --sync-spin-us $spin
  done
  ;;
floor3)  # with the eager detection head too, sync spin 200 us; depth + seg again
  for heads in depth,seg,det depth,seg; do
    floor 280 $heads floor_bound_${heads//,/_}_borrow_spin200_b --sync-spin-us 200
  done
  ;;
esac
ls "$OUT"
