#!/usr/bin/env bash
# GPU machine, Note [Event hand-off] (thread mode: features handed to the heads by CUDA event):
#   tests    the hand-off tests on CUDA (and their CPU twins), the compiled engine test in both modes, slot-bound
#            and frame-slot tests; then profile and floor
#   profile  where one frame's time goes in thread mode, event vs host hand-off (profile_steps.py)
#   floor    the depth + seg floor (compiled, borrowed): event hand-off with sleeping sync and sync spin 200 us,
#            host hand-off with sleeping sync
#   e5       E5 in thread mode with the event hand-off, E5_FRAMES frames (default 10,000)
#   e5p      E5 in process mode (host hand-off there), E5_FRAMES frames; then the floor with detection too
source benchmarks/gpu/setup.sh
case "${1:-tests}" in
tests)
  VPENGINE_TEST_DEVICE=cuda timeout 300 python3 -m pytest -q -p no:cacheprovider -m "gpu or not gpu" \
    tests/gpu/test_event_handoff_cuda.py tests/unit/test_event_handoff.py \
    tests/gpu/test_compile_cuda.py::test_engine_with_compiled_models_on_cuda_matches_eager \
    tests/gpu/test_compile_cuda.py::test_slot_bound_runs_read_and_write_the_slots_they_are_told \
    tests/unit/test_frame_slot.py tests/unit/test_slot_bound.py tests/unit/test_device_sync.py \
    > "$OUT/event_handoff_tests_on_cuda.log" 2>&1; tail -3 "$OUT/event_handoff_tests_on_cuda.log"
  ;;&
tests|profile)
  TAG=_handoff timeout 170 python3 benchmarks/gpu/profile_steps.py 2>&1 | grep -v "RANDOM\|WARNING" \
    > "$OUT/profile_steps_handoff.log"; grep "mean\|slot-bound" "$OUT/profile_steps_handoff.log"
  ;;&
tests|floor)
  for run in "event 0" "host 0" "event 200"; do
    set -- $run
    floor 150 depth,seg floor_handoff_$1_depth_seg_borrow_spin$2 --sync-spin-us $2 --feature-handoff $1
  done
  ;;
e5)
  timeout 560 python3 -m vpengine.cli.main bench paper --experiments E5 --e5-frames ${E5_FRAMES:-10000} \
    --det-head frcnn_dinov2_lite --backend compile --mode thread --tag e5_thread_handoff --out "$OUT" 2>&1 \
    | grep -v "RANDOM\|WARNING" | tail -4
  ;;
e5p)
  timeout 420 python3 -m vpengine.cli.main bench paper --experiments E5 --e5-frames ${E5_FRAMES:-10000} \
    --det-head frcnn_dinov2_lite --backend compile --mode process --tag e5_process_rerun --out "$OUT" 2>&1 \
    | grep -v "RANDOM\|WARNING" | tail -2
  floor 150 depth,seg,det floor_handoff_event_depth_seg_det_borrow_spin0
  ;;
esac
ls "$OUT"
