#!/usr/bin/env bash
# GPU machine: per-stage latencies of the engine in thread and process mode (compiled depth + seg), py-spy samples.
source benchmarks/gpu/setup.sh
python3 -m pip install -q --no-index --no-deps --target /tmp/tools .whl-tools/*.whl 2>&1 | tail -1
export PATH=/tmp/tools/bin:$PATH
timeout 400 python3 benchmarks/gpu/profile_modes.py "$@" 2>&1 | grep -v "RANDOM\|WARNING" | tail -4
