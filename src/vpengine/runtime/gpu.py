"""Device memory as the driver reports it (NVML), per process and per device.

PyTorch's own counters miss the CUDA context and anything allocated outside its caching allocator (our VMM
mailboxes), so constant-memory checks and reports use NVML when it is there (package nvidia-ml-py).
"""

from __future__ import annotations

from typing import Any


def _nvml() -> Any:
    try:
        import pynvml
    except ImportError:
        return None
    try:
        pynvml.nvmlInit()
    except Exception:
        return None
    return pynvml


def process_memory(index: int = 0) -> dict[int, int]:
    """``{pid: bytes}`` of device memory each process uses on GPU ``index`` ({} without NVML)."""
    nv = _nvml()
    if nv is None:
        return {}
    h = nv.nvmlDeviceGetHandleByIndex(index)
    out: dict[int, int] = {}
    for getter in ("nvmlDeviceGetComputeRunningProcesses", "nvmlDeviceGetGraphicsRunningProcesses"):
        try:
            procs = getattr(nv, getter)(h)
        except Exception:
            continue
        for p in procs:
            used = p.usedGpuMemory
            if used is not None:
                out[int(p.pid)] = out.get(int(p.pid), 0) + int(used)
    return out


def device_memory_used(index: int = 0) -> int | None:
    """Bytes in use on GPU ``index`` by everyone (NVML, else cudaMemGetInfo), None without a GPU."""
    nv = _nvml()
    if nv is not None:
        return int(nv.nvmlDeviceGetMemoryInfo(nv.nvmlDeviceGetHandleByIndex(index)).used)
    import torch

    if not torch.cuda.is_available():
        return None
    free, total = torch.cuda.mem_get_info(index)
    return int(total - free)
