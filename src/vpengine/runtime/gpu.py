"""The GPU as the engine sees it: device memory as the driver reports it (NVML), and the CUDA set-up at start
(the device checked, the MPS daemon found, the parent's context made off MPS).

PyTorch's own counters miss the CUDA context and anything allocated outside its caching allocator (our VMM
mailboxes), so constant-memory checks and reports use NVML when it is there (package nvidia-ml-py).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from vpengine.config import EngineConfig

log = logging.getLogger("vpengine")


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


# ---------------------------------------------------------------------------------------------- set-up
#: Note [Thread stack]
#: ~~~~~~~~~~~~~~~~~~~
#: Every CUDA context reserves local memory for the stack of every thread the GPU can hold at once: at CUDA's
#: default of 1 KiB a thread that is about 200 MiB on an H200, a third of a bare context (612 MiB), paid again by
#: each process of the engine. vpengine's kernels need far less, and the driver raises the limit by itself at the
#: first launch of a kernel that needs more (and keeps it), so the processes whose context vpengine creates start
#: with a small stack. Every kernel a worker runs has run once in its warm-up, before READY and before any CUDA
#: graph is captured, so the steady state neither grows it nor allocates (Invariant: constant memory).
STACK_BYTES = 256


def trim_thread_stack(index: int) -> bool:
    """Give the current process's context on GPU ``index`` a small per-thread stack (Note [Thread stack]),
    creating the context if there is none. Only where vpengine owns the context: a worker process, or the parent
    before anything else used CUDA. False without the CUDA Python bindings (nothing changed)."""
    try:
        from cuda.bindings import runtime as rt
    except ImportError:
        log.debug("no cuda-bindings: the CUDA contexts keep their default thread stack")
        return False
    for err, *_ in (rt.cudaSetDevice(index), rt.cudaDeviceSetLimit(rt.cudaLimit.cudaLimitStackSize, STACK_BYTES)):
        if err != rt.cudaError_t.cudaSuccess:
            log.warning("could not shrink the CUDA thread stack on device %d: %r", index, err)
            return False
    return True


@dataclass(frozen=True)
class CudaSetup:
    """What the engine decided about CUDA at start: the MPS daemon its workers use (None: none), and a private,
    empty pipe directory that keeps a worker off MPS."""

    mps_dir: str | None
    nomps_dir: str


def prepare_cuda(cfg: EngineConfig) -> CudaSetup:
    """Check the device, find the MPS daemon, and initialise CUDA here (in the parent) off MPS; raises
    EngineStartError naming what is missing. See Note [MPS and ownership of device memory] in runtime/mps.py.
    The caller removes ``nomps_dir`` at stop."""
    import tempfile

    import torch

    from vpengine.runtime import mps
    from vpengine.runtime.supervisor import EngineStartError

    device = torch.device(cfg.device)
    if not torch.cuda.is_available():
        raise EngineStartError(f"device {cfg.device!r} was asked for but PyTorch sees no CUDA device")
    index = device.index or 0
    if index >= torch.cuda.device_count():
        raise EngineStartError(f"device {cfg.device!r}: only {torch.cuda.device_count()} CUDA device(s) visible")
    mps_dir = mps.find_daemon() if cfg.mps != "off" else None
    if cfg.mps == "required" and mps_dir is None:
        raise EngineStartError(
            f"mps: required, but no MPS control daemon answers in {mps.candidate_dirs()}; "
            "start one with `vpengine mps start` or set mps: auto"
        )
    if not torch.cuda.is_initialized():
        with mps.off_mps():
            torch.cuda.init()
            torch.cuda.set_device(index)
            torch.empty(1, device=device)  # create the context now, while MPS is out of reach
            trim_thread_stack(index)  # ours: nothing else has used CUDA in this process
    if cfg.mode == "process":
        from vpengine.transport.cuda_vmm import CudaVmmError, vmm_support

        try:
            support = vmm_support(index)
        except CudaVmmError as e:
            raise EngineStartError(str(e)) from None
        if not all(support.values()):
            raise EngineStartError(
                f"{cfg.device} cannot share device memory between processes through the CUDA VMM API "
                f"({support}); use mode: thread"
            )
    if mps_dir:
        log.info("CUDA MPS daemon found at %s: model workers will be MPS clients", mps_dir)
    elif hint := no_mps_hint(cfg):
        log.warning(hint)
    return CudaSetup(mps_dir, tempfile.mkdtemp(prefix="vpengine-nomps-"))


def no_mps_hint(cfg: EngineConfig) -> str | None:
    """What to say when process mode on a GPU finds no MPS daemon and the config left the choice open (``mps:
    auto``): without one the workers' kernels take turns on the device instead of running side by side. ``mps:
    off`` is a decision, and one worker has nobody to overlap with: nothing then."""
    workers = 1 + len(cfg.heads)
    if cfg.mode != "process" or cfg.mps != "auto" or workers < 2:
        return None
    return (
        f"process mode without CUDA MPS: the {workers} workers' kernels take turns on the GPU (on an H200, 8 "
        "detection heads took 10.6 ms a frame without MPS, 6.6 ms with it); `vpengine mps start` runs a daemon, "
        "mps: off says you chose this"
    )


def worker_env(cfg: EngineConfig, setup: CudaSetup | None, name: str) -> dict[str, str]:
    """Environment overrides for a worker process, decided at each (re)start: on MPS while its daemon answers."""
    if setup is None:
        return {}
    from vpengine.runtime import mps

    use = setup.mps_dir if setup.mps_dir and mps.status(setup.mps_dir)["reachable"] else None
    env = {"CUDA_MPS_PIPE_DIRECTORY": use or setup.nomps_dir}
    if use:
        from vpengine.runtime.priority import mps_below_normal

        env["CUDA_MPS_CLIENT_PRIORITY"] = "1" if mps_below_normal(cfg, name) else "0"
    elif setup.mps_dir:
        log.warning("MPS daemon at %s no longer answers: %s starts without MPS", setup.mps_dir, name)
    return env
