#!/usr/bin/env bash
# GPU machine: E2 (detection heads, eager Faster R-CNN with the gather-padded outputs), and E1 at 8 heads with
# compiled models once more (run-to-run spread of the compiled E1).
source benchmarks/gpu/setup.sh
timeout 300 python3 -m vpengine.cli.main bench paper --experiments E2 --heads 1,2,4,8 --frames 30 \
  --det-head frcnn_dinov2_lite --tag e2 --out "$OUT" 2>&1 | grep -v "RANDOM\|WARNING" | grep "E2 N=\|Error" | tail -6
timeout 200 python3 -m vpengine.cli.main bench paper --experiments E1 --heads 8 --frames 40 --backend compile \
  --tag e1_vits_compile_n8_rerun --out "$OUT" 2>&1 | grep -v "RANDOM\|WARNING" | grep "E1 N=\|Error" | tail -2
