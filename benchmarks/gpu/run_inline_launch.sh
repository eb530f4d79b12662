#!/usr/bin/env bash
# GPU machine, Note [Inline launch] (thread mode: the submitting thread queues the foundation model's work):
#   tests    its tests on CUDA (the CPU ones too, on CUDA), the event hand-off tests, the foundation fault test, the
#            compiled engine test in both modes, frame-slot tests; then profile
#   profile  where one frame's time goes in thread mode, worker launch vs inline launch (profile_steps.py)
#   floor    the depth + seg floor (compiled, borrowed, event hand-off): inline launch and worker launch, sleeping
#            sync; inline launch with sync spin 200 us
source benchmarks/gpu/setup.sh
case "${1:-tests}" in
tests)
  VPENGINE_TEST_DEVICE=cuda timeout 330 python3 -m pytest -q -p no:cacheprovider -m "gpu or not gpu" \
    tests/gpu/test_inline_launch_cuda.py tests/integration/test_inline_launch.py tests/gpu/test_event_handoff_cuda.py \
    "tests/integration/test_faults.py::test_foundation_raising_is_restarted_and_the_heads_then_get_the_same_features_as_before" \
    tests/gpu/test_compile_cuda.py::test_engine_with_compiled_models_on_cuda_matches_eager tests/unit/test_frame_slot.py \
    > "$OUT/inline_launch_tests_on_cuda.log" 2>&1; tail -3 "$OUT/inline_launch_tests_on_cuda.log"
  ;;&
tests|profile)
  TAG=_inline VARIANTS="slot worker launch,slot+spin200" timeout 240 python3 benchmarks/gpu/profile_steps.py 2>&1 \
    | grep -v "RANDOM\|WARNING" > "$OUT/profile_steps_inline.log"; grep "mean\|slot-bound" "$OUT/profile_steps_inline.log"
  ;;
floor)
  floor 150 depth,seg floor_inline_auto_depth_seg_borrow_spin0
  floor 150 depth,seg floor_inline_never_depth_seg_borrow_spin0 --inline-launch never
  floor 150 depth,seg floor_inline_auto_depth_seg_borrow_spin200 --sync-spin-us 200
  ;;
esac
ls "$OUT"
