#!/usr/bin/env bash
# GPU machine: the gpu-marked tests, then the core integration tests on CUDA. Logs go to $OUT.
source benchmarks/gpu/setup.sh
{
  nvidia-smi --query-gpu=name,driver_version,memory.total,memory.used --format=csv
  python3 -c "import torch, sys; print(sys.version); print('torch', torch.__version__, 'cuda', torch.version.cuda)"
  python3 -c "import cuda.bindings, pynvml; print('cuda-bindings', cuda.bindings.__version__)" 2>&1 | tail -1
  which nvidia-cuda-mps-control
} 2>&1 | tee "$OUT/env.txt"
timeout ${GPU_TEST_TIMEOUT:-420} python3 -m pytest -m gpu tests/gpu -q -p no:cacheprovider "$@" 2>&1 | tee "$OUT/gpu_tests.log" | tail -25
VPENGINE_TEST_DEVICE=cuda timeout ${INTEG_TIMEOUT:-300} python3 -m pytest tests/integration/test_pipeline.py \
  tests/integration/test_ring_processes.py tests/integration/test_faults.py tests/integration/test_rates.py \
  tests/integration/test_idle.py tests/integration/test_input_modes.py -q -p no:cacheprovider 2>&1 | tee "$OUT/integration_cuda.log" | tail -15
