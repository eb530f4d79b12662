#!/usr/bin/env bash
# GPU machine: E2 with the backbone compiled (CUDA graph) and the detection heads eager, in the engine and in the
# sequential baseline alike; with and without CUDA MPS. Then where the time of 1 and 8 detection heads goes.
source benchmarks/gpu/setup.sh
set -o pipefail
paper 240 --experiments E2 --heads 1,8 --frames 30 --det-head frcnn_dinov2_lite --backend compile --mps required \
  --tag e2_compile_mps
paper 200 --experiments E2 --heads 1,8 --frames 30 --det-head frcnn_dinov2_lite --backend compile --tag e2_compile
for n in 1 8; do
  HEADS=det:$n MPS=required TAG=_compile_det${n}_mps timeout 120 python3 benchmarks/gpu/profile_modes.py process 2>&1 \
    | grep -v "RANDOM\|WARNING" | tail -2
done
python3 -m vpengine.cli.main mps stop 2>&1 | tail -1  # in case a timeout cut a run short
ls "$OUT"
