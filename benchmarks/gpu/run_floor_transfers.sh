#!/usr/bin/env bash
# GPU machine: the floor with the transfers a frame needs at least (its upload, the results' download; CUDA events),
# compiled depth + seg, and with eager detection too, results borrowed.
source benchmarks/gpu/setup.sh
for heads in depth,seg depth,seg,det; do
  timeout 120 python3 -m vpengine.cli.main bench paper --experiments floor --floor-heads $heads --backend compile \
    --frames 100 --results borrow --tag floor_xfer_${heads//,/_}_borrow --out "$OUT" 2>&1 | grep "floor:\|Error" | tail -2
done
ls "$OUT"
