#!/usr/bin/env bash
# GPU machine: borrowed results (Engine.wait/results/latest with copy=False). Their tests on CUDA first, then E1 at
# 8 compiled ViT-S depth heads, the depth + seg floor and where E1's time goes, all with --results borrow.
source benchmarks/gpu/setup.sh
set -o pipefail
VPENGINE_TEST_DEVICE=cuda timeout 200 python3 -m pytest tests/integration/test_borrowed_results.py \
  tests/integration/test_pipeline.py tests/unit/test_engine_api.py -q -p no:cacheprovider 2>&1 \
  | tee "$OUT/borrowed_tests_on_cuda.log" | tail -4
paper 170 --experiments E1 --heads 8 --frames 40 --backend compile --results borrow --tag e1_vits_compile_n8_borrow
timeout 120 python3 -m vpengine.cli.main bench paper --experiments floor --floor-heads depth,seg --backend compile \
  --frames 100 --results borrow --tag floor_compile_depth_seg_borrow --out "$OUT" 2>&1 | grep "floor:" | tail -1
HEADS=depth:8 RESULTS=borrow TAG=_compile_depth8_borrow timeout 120 python3 benchmarks/gpu/profile_modes.py process \
  2>&1 | grep -v "RANDOM\|WARNING" | tail -1 | cut -c1-400
ls "$OUT"
