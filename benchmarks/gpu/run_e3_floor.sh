#!/usr/bin/env bash
# GPU machine: CUDA-graph backend tests, E3 (MPS off vs on, eager), floor with compiled models.
source benchmarks/gpu/setup.sh
timeout 170 python3 -m pytest -m gpu tests/gpu/test_compile_cuda.py -q -p no:cacheprovider 2>&1 | tee "$OUT/compile_tests.log" | tail -4
timeout 170 python3 -m vpengine.cli.main bench paper --experiments E3 --frames 40 --det-head frcnn_dinov2_lite \
  --tag e3 --out "$OUT" 2>&1 | grep -v "RANDOM\|WARNING" | tail -5
timeout 200 python3 -m vpengine.cli.main bench paper --experiments floor --frames 60 --det-head frcnn_dinov2_lite \
  --backend compile --tag floor_compile --out "$OUT" 2>&1 | grep -v "RANDOM\|WARNING" | tail -3
