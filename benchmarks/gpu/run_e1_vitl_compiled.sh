#!/usr/bin/env bash
# GPU machine: E1 at 8 heads with ViT-L and its DPT head compiled (CUDA graphs), process mode, MPS off. ViT-L is the
# backbone with the largest share of the work, hence the highest ideal ratio N(b+h)/(b+Nh).
# RUN=b: a repeat under another file name; WITH_VITB=1: then ViT-B the same way.
source benchmarks/gpu/setup.sh
set -o pipefail
paper 560 --experiments E1 --heads 8 --frames 40 --backend compile --backbone dinov2_vitl14_dav2 \
  --depth-head dav2_depth_l --tag e1_vitl_compile_n8${RUN:+_$RUN}
[ -n "${WITH_VITB:-}" ] && paper 300 --experiments E1 --heads 8 --frames 40 --backend compile \
  --backbone dinov2_vitb14_dav2 --depth-head dav2_depth_b --tag e1_vitb_compile_n8
ls "$OUT"
