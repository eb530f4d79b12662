#!/usr/bin/env bash
# GPU machine: E2 for 1, 2, 4, 8 detection heads with the backbone compiled, CUDA MPS on, 100 frames per point;
# then E3 (MPS off vs on, eager, as in paper_cuda_e3.json) through the shared MPS-daemon context.
source benchmarks/gpu/setup.sh
set -o pipefail
paper 250 --experiments E2 --frames 100 --det-head frcnn_dinov2_lite --backend compile --mps required \
  --tag e2_compile_mps_sweep
timeout 200 python3 -m vpengine.cli.main bench paper --experiments E3 --frames 40 --det-head frcnn_dinov2_lite \
  --tag e3_rerun --out "$OUT" 2>&1 | grep "E3 \|MPS daemon\|Error" | tail -6
python3 -m vpengine.cli.main mps stop 2>&1 | tail -1  # in case a timeout cut a run short
ls "$OUT"
