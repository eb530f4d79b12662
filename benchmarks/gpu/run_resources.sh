#!/usr/bin/env bash
# GPU machine: issue-4 resources (device memory per extra head, CPU idle and at 30 Hz), MPS off and on.
source benchmarks/gpu/setup.sh
timeout 280 python3 -m vpengine.cli.main bench resources --config configs/bench_vits_depth.yaml --heads 1,2,4 \
  --seconds 5 --out "$OUT" 2>&1 | grep -v RANDOM | tail -9
python3 -m vpengine.cli.main mps start
timeout 200 python3 -m vpengine.cli.main bench resources --config configs/bench_vits_depth.yaml --heads 1,2,4 \
  --modes process --seconds 5 --set mps=required --out "$OUT" 2>&1 | grep -v RANDOM | tail -6
python3 -m vpengine.cli.main mps stop
