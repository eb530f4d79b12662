#!/usr/bin/env bash
# GPU machine: the engine API and borrowed-result tests on CUDA (after the stats test was fixed).
source benchmarks/gpu/setup.sh
VPENGINE_TEST_DEVICE=cuda timeout 200 python3 -m pytest tests/unit/test_engine_api.py tests/integration/test_borrowed_results.py -q -p no:cacheprovider 2>&1 | tee "$OUT/borrowed_tests_on_cuda_rerun.log" | tail -3
