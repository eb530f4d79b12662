#!/usr/bin/env bash
# GPU machine: E1 (8 compiled depth heads) and E2 (8 eager detection heads) with the engine in thread mode, and with
# CUDA MPS for every process (engine and independent models alike).
source benchmarks/gpu/setup.sh
set -o pipefail
paper 170 --experiments E1 --heads 8 --frames 40 --backend compile --mode thread --tag e1_vits_compile_n8_thread
paper 170 --experiments E1 --heads 8 --frames 40 --backend compile --mps required --tag e1_vits_compile_n8_mps
paper 90 --experiments E2 --heads 8 --frames 30 --det-head frcnn_dinov2_lite --mps required --tag e2_n8_mps
paper 90 --experiments E2 --heads 8 --frames 30 --det-head frcnn_dinov2_lite --mode thread --tag e2_n8_thread
python3 -m vpengine.cli.main mps stop 2>&1 | tail -1  # in case a timeout cut a run short
ls "$OUT"
