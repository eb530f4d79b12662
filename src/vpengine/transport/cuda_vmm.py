"""Device memory shared across processes through the CUDA virtual memory management (VMM) API.

Note [CUDA VMM sharing]
~~~~~~~~~~~~~~~~~~~~~~~
A pool is one physical allocation made with ``cuMemCreate`` and requested as shareable through a POSIX file
descriptor. The creating process exports that descriptor once (``cuMemExportToShareableHandle``); it travels to each
child over the child's socketpair with SCM_RIGHTS (like the memfds of host pools), and the child imports it
(``cuMemImportFromShareableHandle``), reserves a virtual range, maps it and grants itself read/write access. Every
process then holds a plain device pointer to the same bytes, wrapped as a torch tensor through
``__cuda_array_interface__`` with no copy.

Why not torch's CUDA tensor pickling or ``cudaIpc*``: legacy CUDA IPC is unavailable on Jetson (Tegra) and ties the
allocation to torch's caching allocator; VMM handles work on Jetson (JetPack 5+) and discrete GPUs alike, and the
memory lives exactly as long as some process maps it or holds its descriptor -- so a restarted worker can map it
again from the descriptor the parent keeps.

Only this module and ``memory.py`` touch these driver calls (see ARCHITECTURE: only transport/ and runtime/ do).
"""

from __future__ import annotations

import os
import threading
from typing import Any

import torch

from vpengine.transport.region import Region, RegionHandle

_lock = threading.Lock()


class CudaVmmError(RuntimeError):
    pass


def _driver() -> Any:
    import importlib

    for module in ("cuda.bindings.driver", "cuda.cuda"):  # cuda-bindings >= 12.6, older cuda-python
        try:
            return importlib.import_module(module)
        except ImportError:
            continue
    raise CudaVmmError(
        "process mode on CUDA shares device memory through the CUDA VMM API and needs the CUDA Python bindings: "
        "pip install 'vpengine[cuda]' (cuda-bindings), or use mode: thread"
    )


def _check(result: Any, what: str) -> Any:
    d = _driver()
    err, *rest = result if isinstance(result, tuple) else (result,)
    if err != d.CUresult.CUDA_SUCCESS:
        _, name = d.cuGetErrorName(err)
        _, text = d.cuGetErrorString(err)
        raise CudaVmmError(f"{what} failed: {name.decode() if name else err}: {text.decode() if text else ''}")
    if not rest:
        return None
    return rest[0] if len(rest) == 1 else tuple(rest)


def _current_context(index: int) -> Any:
    """Make the device's primary context (the one PyTorch uses) current in this thread."""
    d = _driver()
    _check(d.cuInit(0), "cuInit")
    dev = _check(d.cuDeviceGet(index), f"cuDeviceGet({index})")
    _sleep_in_waits(d, dev)
    torch.cuda.init()
    ctx = _check(d.cuDevicePrimaryCtxRetain(dev), "cuDevicePrimaryCtxRetain")
    _check(d.cuCtxSetCurrent(ctx), "cuCtxSetCurrent")
    return dev


def _sleep_in_waits(d: Any, dev: Any) -> None:
    """Note [Sleeping waits]: a process that shares device memory through this module (process mode) waits for
    its device asleep, not spinning. With the default scheduling (CU_CTX_SCHED_AUTO) a process whose contexts are
    fewer than the machine's cores spins a core in every wait that is not on a blocking event, so each worker
    process burnt a core for its GPU's whole work. Set on the primary context before it is created; where it
    already is (the parent, which made it off MPS first), the waits there are few and the error is ignored."""
    flags, active = _check(d.cuDevicePrimaryCtxGetState(dev), "cuDevicePrimaryCtxGetState")
    sched = int(d.CUctx_flags.CU_CTX_SCHED_MASK)
    want = (int(flags) & ~sched) | int(d.CUctx_flags.CU_CTX_SCHED_BLOCKING_SYNC)
    if int(flags) != want and not active:
        _check(d.cuDevicePrimaryCtxSetFlags(dev, want), "cuDevicePrimaryCtxSetFlags")


def vmm_support(index: int = 0) -> dict[str, bool]:
    """Whether device ``index`` supports VMM and POSIX file-descriptor handles (needed for process mode)."""
    d = _driver()
    dev = _current_context(index)
    attrs = d.CUdevice_attribute
    vmm = _check(d.cuDeviceGetAttribute(attrs.CU_DEVICE_ATTRIBUTE_VIRTUAL_MEMORY_MANAGEMENT_SUPPORTED, dev), "attr")
    fd = _check(
        d.cuDeviceGetAttribute(attrs.CU_DEVICE_ATTRIBUTE_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR_SUPPORTED, dev),
        "attr",
    )
    return {"vmm": bool(vmm), "posix_fd": bool(fd)}


def mps_enabled(index: int = 0) -> bool:
    """Whether this process's contexts on device ``index`` run through a CUDA MPS server."""
    d = _driver()
    dev = _current_context(index)
    attr = getattr(d.CUdevice_attribute, "CU_DEVICE_ATTRIBUTE_MPS_ENABLED", None)
    if attr is None:
        return False
    return bool(_check(d.cuDeviceGetAttribute(attr, dev), "cuDeviceGetAttribute(MPS_ENABLED)"))


class _CudaArray:
    """The smallest object torch.as_tensor accepts as device memory without a copy."""

    def __init__(self, ptr: int, nbytes: int) -> None:
        self.__cuda_array_interface__ = {
            "shape": (nbytes,),
            "typestr": "|u1",
            "data": (ptr, False),
            "version": 3,
            "strides": None,
        }


class CudaVmmRegion(Region):
    """One VMM allocation, mapped in this process, exportable as a POSIX file descriptor."""

    kind = "cuda-vmm"

    def __init__(self, name: str, nbytes: int, device: torch.device | str, *, import_fd: int | None = None) -> None:
        device = torch.device(device)
        index = device.index if device.index is not None else torch.cuda.current_device()
        super().__init__(name, nbytes, torch.device("cuda", index))
        d = _driver()
        self._index = index
        self._fd: int | None = None
        self._handle: Any = None
        self._ptr: Any = None
        self._tensor: torch.Tensor | None = None
        with _lock:
            dev = _current_context(index)
            support = vmm_support(index)
            if not all(support.values()):
                raise CudaVmmError(
                    f"cuda:{index} does not support sharing device memory between processes through the VMM API "
                    f"({support}); use mode: thread on this device"
                )
            prop = d.CUmemAllocationProp()
            prop.type = d.CUmemAllocationType.CU_MEM_ALLOCATION_TYPE_PINNED
            prop.location.type = d.CUmemLocationType.CU_MEM_LOCATION_TYPE_DEVICE
            prop.location.id = index
            prop.requestedHandleTypes = d.CUmemAllocationHandleType.CU_MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR
            gran = _check(
                d.cuMemGetAllocationGranularity(
                    prop, d.CUmemAllocationGranularity_flags.CU_MEM_ALLOC_GRANULARITY_RECOMMENDED
                ),
                "cuMemGetAllocationGranularity",
            )
            self.alloc_bytes = max(gran, (nbytes + gran - 1) // gran * gran)
            try:
                if import_fd is None:
                    self._handle = _check(d.cuMemCreate(self.alloc_bytes, prop, 0), f"cuMemCreate({self.alloc_bytes})")
                    self._fd = int(
                        _check(
                            d.cuMemExportToShareableHandle(
                                self._handle,
                                d.CUmemAllocationHandleType.CU_MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR,
                                0,
                            ),
                            "cuMemExportToShareableHandle",
                        )
                    )
                else:
                    self._handle = _check(
                        d.cuMemImportFromShareableHandle(
                            import_fd, d.CUmemAllocationHandleType.CU_MEM_HANDLE_TYPE_POSIX_FILE_DESCRIPTOR
                        ),
                        "cuMemImportFromShareableHandle",
                    )
                self._ptr = _check(d.cuMemAddressReserve(self.alloc_bytes, 0, 0, 0), "cuMemAddressReserve")
                _check(d.cuMemMap(self._ptr, self.alloc_bytes, 0, self._handle, 0), "cuMemMap")
                access = d.CUmemAccessDesc()
                access.location.type = d.CUmemLocationType.CU_MEM_LOCATION_TYPE_DEVICE
                access.location.id = index
                access.flags = d.CUmemAccess_flags.CU_MEM_ACCESS_FLAGS_PROT_READWRITE
                _check(d.cuMemSetAccess(self._ptr, self.alloc_bytes, [access], 1), "cuMemSetAccess")
            except BaseException:
                self._release()
                raise
            del dev
        self._tensor = torch.as_tensor(_CudaArray(int(self._ptr), self.alloc_bytes), device=self.device)[:nbytes]

    @property
    def ptr(self) -> int:
        return int(self._ptr)

    def tensor(self) -> torch.Tensor:
        if self._tensor is None:
            raise ValueError(f"region {self.name!r} is closed")
        return self._tensor

    def export(self, fds: list[int]) -> RegionHandle:
        if self._fd is None:
            raise TypeError(f"region {self.name!r} was imported and cannot be re-exported")
        fds.append(self._fd)
        return RegionHandle(self.kind, self.name, self.nbytes, len(fds) - 1, self._index, self.alloc_bytes)

    @classmethod
    def open(cls, handle: RegionHandle, fds: list[int]) -> CudaVmmRegion:
        """Map a region exported by another process. Consumes (closes) its descriptor."""
        fd = fds[handle.fd_index]
        try:
            return cls(handle.name, handle.nbytes, torch.device("cuda", handle.device), import_fd=fd)
        finally:
            os.close(fd)  # the imported handle keeps the allocation alive

    def _release(self) -> None:
        d = _driver()
        if self._ptr is not None:
            d.cuMemUnmap(self._ptr, self.alloc_bytes)
            d.cuMemAddressFree(self._ptr, self.alloc_bytes)
            self._ptr = None
        if self._handle is not None:
            d.cuMemRelease(self._handle)
            self._handle = None
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def close(self) -> None:
        """Unmap and release this process's reference. Device work using it must be complete."""
        if self._tensor is None and self._ptr is None:
            return
        self._tensor = None
        with _lock:
            torch.cuda.synchronize(self.device)
            self._release()
