"""Note [Thread stack] in runtime/gpu.py: the contexts vpengine creates reserve less device memory, and kernels that
need a larger stack still get it."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

_PROBE = r"""
import json, os, sys
import torch
from vpengine.runtime.gpu import process_memory, trim_thread_stack
trimmed = sys.argv[1] == "trim" and trim_thread_stack(0)
x = torch.randn(512, 512, device="cuda")
y = (x @ x).sum().item()  # cuBLAS, then a reduction: ordinary kernels run on the small stack
# a sort of many keys runs CUB kernels with a deep per-thread stack frame: the driver grows the stack for it
s = torch.sort(torch.randn(1 << 22, device="cuda")).values
assert bool((s[1:] >= s[:-1]).all())
torch.cuda.synchronize()
from cuda.bindings import runtime as rt
err, limit = rt.cudaDeviceGetLimit(rt.cudaLimit.cudaLimitStackSize)
print(json.dumps({"trimmed": bool(trimmed), "limit": int(limit), "bytes": process_memory(0).get(os.getpid())}))
"""


def _probe(how: str) -> dict:
    out = subprocess.run([sys.executable, "-c", _PROBE, how], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_trimmed_context_holds_less_memory_and_still_runs_every_kernel(require_cuda):
    pytest.importorskip("cuda.bindings")
    pytest.importorskip("pynvml")
    plain, trimmed = _probe("plain"), _probe("trim")
    assert trimmed["trimmed"] and not plain["trimmed"]
    assert plain["limit"] == 1024  # CUDA's default: what an untrimmed context reserves for
    assert trimmed["limit"] < plain["limit"]
    # about 200 MiB on an H100/H200; the bound leaves room for smaller GPUs
    assert plain["bytes"] - trimmed["bytes"] >= 32 * 2**20, (plain, trimmed)
