"""Memory backends: where a slot pool lives, and how another process maps the same bytes.

A :class:`~vpengine.transport.region.Region` is one contiguous allocation (one per pool, carved into slots and keys by ``layout.py``) that can
be viewed as a flat ``uint8`` torch tensor without a copy. Process mode needs regions that other processes can map:
``export`` appends the file descriptors that stand for the region to a list (sent later over a UNIX socket with
SCM_RIGHTS) and returns a small picklable :class:`RegionHandle`; ``open_region`` in the child turns both back into a
mapped region.

Backends:

* ``host``: a memfd (anonymous shared memory, owner-only, never in /dev/shm) mapped with mmap. CPU mode, CI, input
  frames and host-side result slots.
* ``local``: a plain torch allocation on any device, for thread mode (one process, nothing to share).
* ``cuda-vmm``: device memory from the CUDA virtual memory API, exported as a POSIX file descriptor
  (``cuda_vmm.py``; imported lazily so CPU installs never touch CUDA).
"""

from __future__ import annotations

import mmap
import os

import torch

from vpengine.transport import linux
from vpengine.transport.region import Region, RegionHandle


class HostRegion(Region):
    """Shared host memory: memfd + mmap. Owner-only by construction, freed when the last process unmaps it."""

    kind = "host"

    def __init__(self, name: str, nbytes: int, fd: int | None = None, keep_fd: bool = True) -> None:
        super().__init__(name, nbytes, torch.device("cpu"))
        owns = fd is None
        self._fd: int | None = linux.memfd(name, max(nbytes, 1)) if fd is None else fd
        try:
            self._mm: mmap.mmap | None = mmap.mmap(self._fd, max(nbytes, 1))
        except BaseException:
            if owns:
                os.close(self._fd)
            raise
        if not keep_fd:
            os.close(self._fd)
            self._fd = None
        self._tensor: torch.Tensor | None = None
        self.cuda_registered = False

    @property
    def mm(self) -> mmap.mmap:
        if self._mm is None:
            raise ValueError(f"region {self.name!r} is closed")
        return self._mm

    def tensor(self) -> torch.Tensor:
        if self._tensor is None:
            self._tensor = torch.frombuffer(self.mm, dtype=torch.uint8, count=self.nbytes)
        return self._tensor

    def address(self) -> int:
        return linux.address_of(self.mm, 0)

    def keep_mapped(self) -> object:
        # A buffer export: while it lives, mmap.close() refuses (BufferError) and the mapping goes with the last
        # reference. torch.frombuffer's tensors do not hold one, so they alone would not keep it mapped.
        return memoryview(self.mm)

    def export(self, fds: list[int]) -> RegionHandle:
        if self._fd is None:
            raise TypeError(f"region {self.name!r} was opened without its descriptor and cannot be re-exported")
        fds.append(self._fd)
        return RegionHandle(self.kind, self.name, self.nbytes, len(fds) - 1)

    @classmethod
    def open(cls, handle: RegionHandle, fds: list[int]) -> HostRegion:
        return cls(handle.name, handle.nbytes, fd=fds[handle.fd_index], keep_fd=False)

    def register_with_cuda(self) -> None:
        """Page-lock this mapping for the GPU (cudaHostRegister) so copies to and from it run asynchronously."""
        if self.cuda_registered or not torch.cuda.is_available():
            return
        rc = torch.cuda.cudart().cudaHostRegister(self.address(), self.nbytes, 0)
        if int(rc) != 0:
            raise RuntimeError(f"cudaHostRegister failed for region {self.name!r} ({self.nbytes} bytes): {rc}")
        self.cuda_registered = True

    def close(self) -> None:
        if self.cuda_registered and self._mm is not None:
            torch.cuda.cudart().cudaHostUnregister(self.address())
            self.cuda_registered = False
        self._tensor = None
        if self._mm is not None:
            try:
                self._mm.close()
            except BufferError:
                # A borrowed result still holds the mapping (keep_mapped); it is unmapped when that goes.
                pass
            self._mm = None
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


class LocalRegion(Region):
    """A plain allocation in this process (thread mode): host or device, never shared.

    ``pinned`` host memory (page-locked) is what lets copies between it and a GPU run asynchronously on a worker's
    stream; from pageable memory the same ``copy_(non_blocking=True)`` silently blocks the calling thread (measured
    on an H100: thread mode 3 ms slower per frame with 1080p depth and segmentation outputs).
    """

    kind = "local"

    def __init__(self, name: str, nbytes: int, device: torch.device, pinned: bool = False) -> None:
        super().__init__(name, nbytes, device)
        pin = pinned and torch.device(device).type == "cpu"
        self._tensor: torch.Tensor | None = torch.empty(
            max(nbytes, 1), dtype=torch.uint8, device=device, pin_memory=pin
        )[:nbytes]
        # The device as the memory's own, indexed (a bare "cuda" becomes "cuda:N", N the current device), as a
        # shared region's is: a worker compares it with its own indexed device to read its inputs in place, and a
        # bare "cuda" compares unequal to every "cuda:N".
        self.device = self._tensor.device

    def tensor(self) -> torch.Tensor:
        if self._tensor is None:
            raise ValueError(f"region {self.name!r} is closed")
        return self._tensor

    def keep_mapped(self) -> object:
        return self.tensor()  # the storage lives while any tensor of it does

    def close(self) -> None:
        self._tensor = None


def _read_int(path: str, prefix: str = "") -> int | None:
    """The first integer in file ``path`` (on the line starting with ``prefix``), or None."""
    try:
        with open(path) as f:
            for line in f:
                if line.startswith(prefix):
                    word = line[len(prefix) :].split()[0]
                    return int(word) if word.isdigit() else None
    except (OSError, IndexError):
        pass
    return None


def free_bytes(device: torch.device) -> int | None:
    """Bytes that can be allocated on ``device`` now: for the host, the kernel's estimate of what is available
    without swapping (``MemAvailable``), less if this process's cgroup allows less; for a CUDA device, its free
    memory. None where it cannot be told."""
    if device.type == "cuda":
        try:
            return int(torch.cuda.mem_get_info(device)[0])
        except (RuntimeError, AssertionError):
            return None
    if device.type != "cpu":
        return None
    kb = _read_int("/proc/meminfo", "MemAvailable:")
    free = None if kb is None else kb * 1024
    limit, used = _read_int("/sys/fs/cgroup/memory.max"), _read_int("/sys/fs/cgroup/memory.current")
    if limit is not None and used is not None:  # cgroup v2 with a limit ("max": none)
        free = limit - used if free is None else min(free, limit - used)
    return free


def allocate(name: str, nbytes: int, device: torch.device | str, shared: bool, pinned: bool = False) -> Region:
    """Allocate a region on ``device``. ``shared`` regions can be exported to other processes.

    ``pinned``: host memory that GPU copies read or write. A local region is allocated page-locked; a shared one is
    page-locked by each process that maps it (``HostRegion.register_with_cuda``, done by the GPU workers).
    """
    device = torch.device(device)
    if device.type == "cpu":
        return HostRegion(name, nbytes) if shared else LocalRegion(name, nbytes, device, pinned)
    if device.type == "cuda":
        if not shared:
            return LocalRegion(name, nbytes, device)
        from vpengine.transport.cuda_vmm import CudaVmmRegion

        return CudaVmmRegion(name, nbytes, device)
    raise ValueError(f"unsupported device {str(device)!r}; accepted: 'cpu', 'cuda', 'cuda:N'")


def open_region(handle: RegionHandle, fds: list[int]) -> Region:
    """Map a region exported by another process. Consumes (closes) the descriptor it uses from ``fds``."""
    if handle.kind == "host":
        return HostRegion.open(handle, fds)
    if handle.kind == "cuda-vmm":
        from vpengine.transport.cuda_vmm import CudaVmmRegion

        return CudaVmmRegion.open(handle, fds)
    raise ValueError(f"unknown region kind {handle.kind!r} for region {handle.name!r}")
