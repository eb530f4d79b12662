#!/usr/bin/env bash
# GPU machine: E1 sweep with compiled models (ViT-S), then the resources run (thread mode has page-locked mailboxes).
source benchmarks/gpu/setup.sh
timeout 290 python3 -m vpengine.cli.main bench paper --experiments E1 --heads 1,2,4,8 --frames 40 --backend compile \
  --tag e1_vits_compile --out "$OUT" 2>&1 | grep -v "RANDOM\|WARNING" | grep "E1 N=\|Error" | tail -6
timeout 280 python3 -m vpengine.cli.main bench resources --config configs/bench_vits_depth.yaml --heads 1,2,4 \
  --seconds 5 --out "$OUT" 2>&1 | grep -v RANDOM | tail -9
