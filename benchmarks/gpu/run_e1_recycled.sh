#!/usr/bin/env bash
# GPU machine: with result arrays recycled (no fresh host memory per result), where the time goes with 8 compiled
# depth heads, then E1 at 8 heads twice in process mode and once in thread mode.
source benchmarks/gpu/setup.sh
set -o pipefail
HEADS=depth:8 TAG=_compile_depth8_recycled timeout 150 python3 benchmarks/gpu/profile_modes.py process 2>&1 \
  | grep -v "RANDOM\|WARNING" | tail -2
for tag in a b; do
  paper 140 --experiments E1 --heads 8 --frames 40 --backend compile --tag "e1_vits_compile_n8_recycled_$tag"
done
paper 150 --experiments E1 --heads 8 --frames 40 --backend compile --mode thread --tag e1_vits_compile_n8_recycled_thread
ls "$OUT"
