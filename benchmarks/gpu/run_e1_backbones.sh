#!/usr/bin/env bash
# GPU machine: E1 at 8 heads for larger backbones (eager) and for ViT-S with compiled models (CUDA graphs).
# The ideal ratio N(b+h)/(b+Nh) grows with the backbone's share of the work, so the backbone size decides what
# E1 can show; each run reports its own ideal from measured device times.
source benchmarks/gpu/setup.sh
P="python3 -m vpengine.cli.main bench paper --experiments E1 --heads ${HEADS:-8} --frames ${FRAMES:-40} --out $OUT"
run() { timeout "$1" $P "${@:2}" 2>&1 | grep -v "RANDOM\|WARNING" | tail -3; }
run 170 --backbone dinov2_vitl14_dav2 --depth-head dav2_depth_l --tag e1_vitl
run 140 --backbone dinov2_vitb14_dav2 --depth-head dav2_depth_b --tag e1_vitb
run 230 --backend compile --tag e1_vits_compile
# The floor with only the models that compile into CUDA graphs (Faster R-CNN's NMS does not): what thread mode costs
# over the device time when no eager Python competes for the GIL.
timeout 150 python3 -m vpengine.cli.main bench paper --experiments floor --floor-heads depth,seg --backend compile \
  --frames 60 --tag floor_compile_depth_seg --out "$OUT" 2>&1 | grep -v "RANDOM\|WARNING" | tail -2
