#!/usr/bin/env bash
# GPU machine: E5 (30 Hz, 1080p, depth + seg + det, compiled backbone/depth/seg) for FRAMES frames, slot-bound vs not,
# one after the other on one machine: does binding the compiled models to the mailbox slots change the stream?
source benchmarks/gpu/setup.sh
E5="python3 -m vpengine.cli.main bench paper --experiments E5 --e5-frames ${FRAMES:-3000} --det-head frcnn_dinov2_lite --backend compile --out $OUT"
for run in bound_a unbound bound_b; do
  extra=""; [ $run = unbound ] && extra="--no-slot-bound"
  timeout 170 $E5 $extra --tag e5_ab_$run 2>&1 | grep "E5 .* at 30 Hz\|Error" | tail -2
done
