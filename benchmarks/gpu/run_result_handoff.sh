#!/usr/bin/env bash
# GPU machine, Note [Result hand-off] (heads publish queued results with a CUDA event; Engine.wait sleeps on it):
#   tests    its tests on CUDA (tests/gpu/test_event_handoff_cuda.py: results and features, event vs host)
#   profile  where one frame's time goes, results handed off by event vs on the host, one engine (profile_steps.py)
#   ab       its variants alternated round by round on one engine (ab_result_handoff.py)
#   trace    one frame-slot profile with its device trace kept (profile_steps.py; PRIORITIES as there)
#   floor    the depth + seg floor, results handed off by event (the default), twice
#   floor_spin  the same with runtime.wait_spin_us 200 (the default since the poll), twice
#   floor_sleep the same with runtime.wait_spin_us 0 (the default before the poll), twice
#   floor_host  the same with results handed off on the host, once
#   floor_det   the floor with detection too
#   suite    every gpu test (tests/gpu)
# SUFFIX names a second run's files (e.g. SUFFIX=_letgo)
#   e5       E5 (10,000 frames at 30 Hz, depth + seg + det)
source benchmarks/gpu/setup.sh
for part in "$@"; do
case "$part" in
tests)
  timeout 240 python3 -m pytest -m gpu -q -p no:cacheprovider tests/gpu/test_event_handoff_cuda.py \
    > "$OUT/result_handoff_tests.log" 2>&1
  tail -n 3 "$OUT/result_handoff_tests.log"
  ;;
profile)
  TAG=_result_handoff${SUFFIX:-} VARIANTS="slot results on host" timeout 200 python3 benchmarks/gpu/profile_steps.py 2>&1 \
    | grep -v "RANDOM\|WARNING" > "$OUT/profile_steps_result_handoff${SUFFIX:-}.log"
  grep "mean\|Error" "$OUT/profile_steps_result_handoff${SUFFIX:-}.log"
  rm -f "$OUT/profile_steps_trace.json.gz"
  ;;
trace)
  VARIANTS=slot TAG=_trace${SUFFIX:-} timeout 300 python3 benchmarks/gpu/profile_steps.py 2>&1 \
    | grep -v "RANDOM\|WARNING" | grep "^slot\|Error"
  mv "$OUT/profile_steps_trace.json.gz" "$OUT/profile_steps_trace${SUFFIX:-}.json.gz"
  ;;
ab)
  ROUNDS=${ROUNDS:-10} TAG=${SUFFIX:-} VARIANTS=${VARIANTS:-} timeout 420 python3 benchmarks/gpu/ab_result_handoff.py 2>&1 \
    | grep -v "RANDOM\|WARNING" | tail -12
  ;;
floor)
  floor 170 depth,seg floor_result_handoff${SUFFIX:-}_depth_seg_a
  floor 170 depth,seg floor_result_handoff${SUFFIX:-}_depth_seg_b
  ;;
floor_spin)
  floor 170 depth,seg floor_result_handoff_wait_spin${SUFFIX:-}_depth_seg_a --wait-spin-us 200
  floor 170 depth,seg floor_result_handoff_wait_spin${SUFFIX:-}_depth_seg_b --wait-spin-us 200
  ;;
floor_sleep)
  floor 170 depth,seg floor_result_handoff_wait_sleep${SUFFIX:-}_depth_seg_a --wait-spin-us 0
  floor 170 depth,seg floor_result_handoff_wait_sleep${SUFFIX:-}_depth_seg_b --wait-spin-us 0
  ;;
floor_host)
  floor 170 depth,seg floor_result_handoff_host${SUFFIX:-}_depth_seg --result-handoff host
  ;;
floor_det)
  floor 220 depth,seg,det floor_result_handoff${SUFFIX:-}_depth_seg_det
  ;;
suite)
  timeout 420 python3 -m pytest -m gpu tests/gpu -q -p no:cacheprovider > "$OUT/gpu_tests_result_handoff.log" 2>&1
  tail -n 3 "$OUT/gpu_tests_result_handoff.log"
  ;;
e5)
  timeout 520 python3 -m vpengine.cli.main bench paper --experiments E5 --e5-frames "${E5_FRAMES:-10000}" \
    --det-head frcnn_dinov2_lite --backend compile --tag "e5_result_handoff${SUFFIX:-}" --out "$OUT" 2>&1 \
    | grep -v "RANDOM\|WARNING" | tail -4
  ;;
esac
done
ls "$OUT"
