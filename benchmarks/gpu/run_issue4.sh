#!/usr/bin/env bash
# GPU machine: GPU tests, then the issue-4 benchmarks and a smoke run of the paper harness. Results under $OUT.
source benchmarks/gpu/setup.sh
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader > "$OUT/env.txt"
timeout 300 python3 -m pytest -m gpu tests/gpu/test_engine_gpu.py -q -p no:cacheprovider 2>&1 | tee "$OUT/gpu_tests.log" | tail -6
timeout 60 python3 -m vpengine.cli.main bench hop --device cuda --layout vits-1080p --hops 10000 --out "$OUT" 2>&1 | tail -1
timeout 240 python3 -m vpengine.cli.main bench resources --config configs/bench_vits_depth.yaml --heads 1,2,4 \
  --seconds 5 --out "$OUT" 2>&1 | grep -v RANDOM | tail -8
timeout 150 python3 -m vpengine.cli.main bench paper --experiments E1,E2,floor --heads 1,2 --frames 20 \
  --tag smoke --out "$OUT" 2>&1 | grep -v RANDOM | tail -12
