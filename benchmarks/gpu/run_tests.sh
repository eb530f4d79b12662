#!/usr/bin/env bash
# GPU machine: the gpu-marked tests, then the core integration tests on CUDA. Logs go to $OUT.
source benchmarks/gpu/setup.sh
# the DINOv2 engine tests read a 1080p frame from ../shared/data/media, which does not travel: carry it in .media/
# (cp ../shared/data/media/cheetah_1080p_0.jpg .media/ here, with /.media/ in .git/info/exclude)
if [ -d .media ]; then mkdir -p ../shared/data/media && cp .media/* ../shared/data/media/; fi
{
  nvidia-smi --query-gpu=name,driver_version,memory.total,memory.used --format=csv
  python3 -c "import torch, sys; print(sys.version); print('torch', torch.__version__, 'cuda', torch.version.cuda)"
  python3 -c "import cuda.bindings, pynvml; print('cuda-bindings', cuda.bindings.__version__)" 2>&1 | tail -1
  which nvidia-cuda-mps-control
} 2>&1 | tee "$OUT/env.txt"
timeout ${GPU_TEST_TIMEOUT:-420} python3 -m pytest -m gpu tests/gpu -q -p no:cacheprovider "$@" 2>&1 | tee "$OUT/gpu_tests.log" | tail -25
VPENGINE_TEST_DEVICE=cuda timeout ${INTEG_TIMEOUT:-300} python3 -m pytest tests/integration/test_pipeline.py \
  tests/integration/test_ring_processes.py tests/integration/test_faults.py tests/integration/test_rates.py \
  tests/integration/test_idle.py tests/integration/test_input_modes.py tests/integration/test_dinov2_engine.py -q -p no:cacheprovider 2>&1 | tee "$OUT/integration_tests_on_cuda.log" | tail -15
