#!/usr/bin/env bash
# GPU machine: engine overhead over the device-time floor (compiled models), per-stage latencies per mode.
source benchmarks/gpu/setup.sh
timeout 120 python3 -m pytest -m gpu tests/gpu/test_engine_gpu.py -k page_locked -q -p no:cacheprovider 2>&1 | tail -2
timeout 150 python3 benchmarks/gpu/profile_modes.py 2>&1 | grep -v "RANDOM\|WARNING\|trained on" | tail -2
F="python3 -m vpengine.cli.main bench paper --experiments floor --backend compile --frames 100 --out $OUT"
timeout 150 $F --floor-heads depth,seg --tag floor_compile_depth_seg 2>&1 | grep -v "RANDOM\|WARNING" | tail -2
timeout 170 $F --det-head frcnn_dinov2_lite --tag floor_compile 2>&1 | grep -v "RANDOM\|WARNING" | tail -2
