#!/usr/bin/env bash
# GPU machine: the paper's experiments E1-E4 and the device-time floor (E5 and E6 run separately).
source benchmarks/gpu/setup.sh
timeout ${PAPER_TIMEOUT:-560} python3 -m vpengine.cli.main bench paper --experiments ${EXPERIMENTS:-E1,E2,E3,E4,floor} \
  --heads ${HEADS:-1,2,4,8} --frames ${FRAMES:-50} --det-head frcnn_dinov2_lite --out "$OUT" "$@" 2>&1 \
  | grep -v "RANDOM\|WARNING" | tee "$OUT/paper.log" | tail -25
