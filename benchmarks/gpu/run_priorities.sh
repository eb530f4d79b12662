#!/usr/bin/env bash
# GPU machine: the order in which concurrent heads finish, and the chained floor.
#   floor    the depth + seg floor (compiled, borrowed), twice each, alternating: default stream priorities, then
#            depth's stream above seg's (--stream-priorities depth=-1), so the larger download (depth, float32) leaves
#            while seg still computes; every run also times the chained floor (all graphs back to back, one stream)
#   profile  where one frame's time goes (profile_steps.py, frame slot), with default priorities and depth first
#   tests    a model's stream_priority is its CUDA stream's, in thread and process mode
source benchmarks/gpu/setup.sh
case "${1:-all}" in
all|floor)
  for run in a b; do
    floor 150 depth,seg "floor_chained_depth_seg_$run"
    floor 150 depth,seg "floor_chained_depth_seg_depth_first_$run" --stream-priorities depth=-1
  done
  ;;&
all|profile)
  for p in default depth_first; do
    prio=""; [ "$p" = depth_first ] && prio="depth=-1"
    TAG="_priority_$p" PRIORITIES="$prio" VARIANTS=slot timeout 200 python3 benchmarks/gpu/profile_steps.py \
      2>&1 | grep -v "RANDOM\|WARNING" > "$OUT/profile_steps_priority_$p.log"; grep "mean" "$OUT/profile_steps_priority_$p.log"
  done
  ;;
esac
case "${1:-all}" in
all|tests)
  timeout 200 python3 -m pytest -m gpu -q -p no:cacheprovider tests/gpu/test_engine_gpu.py -k stream_priority \
    > "$OUT/stream_priority_tests.log" 2>&1; tail -n 3 "$OUT/stream_priority_tests.log"
  ;;
esac
ls "$OUT"
