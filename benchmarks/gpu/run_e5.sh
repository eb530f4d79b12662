#!/usr/bin/env bash
# GPU machine: E5, a 30 Hz stream of 1080p frames with depth, segmentation and detection, 10,000 frames.
source benchmarks/gpu/setup.sh
set -o pipefail
E5="python3 -m vpengine.cli.main bench paper --experiments E5 --e5-frames ${E5_FRAMES:-10000} --det-head frcnn_dinov2_lite --out $OUT"
timeout 500 $E5 --backend compile --tag e5 2>&1 | grep -v "RANDOM\|WARNING" | tail -4 \
  || timeout 450 $E5 --backend eager --tag e5_eager 2>&1 | grep -v "RANDOM\|WARNING" | tail -4
