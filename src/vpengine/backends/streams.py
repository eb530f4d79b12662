"""CUDA streams lent to workers and executors, and taken back when their holder is gone.

Note [Reused streams]
~~~~~~~~~~~~~~~~~~~~~
cuBLAS keeps a workspace (32 MiB on Hopper) for every (handle, stream) pair it ran on, in a process-wide map that
nothing but ``torch._C._cuda_clearCublasWorkspaces`` empties, and a cuBLAS handle belongs to a thread (handed to the
next thread when its thread ends). A thread-mode worker runs on a stream of its own and, with the compile backend,
captures its CUDA graphs on another: were they new streams each time, every head added at run time (and every
restart) would leave two workspaces behind for good (an H200 kept 71 MB per add/remove cycle of a compiled head,
seen in benchmarks/results/h200/heads_cuda_thread.json). Clearing the map is no cure: it is process-wide, and a
serving model's CUDA graph captured cuBLAS calls with its workspace's address, so freeing that workspace under it
would let the next allocation overwrite what the graph reads and writes.

So streams are lent: ``lend`` gives the stream its last holder (same device and priority) no longer needs, else a
new one, and takes it back once the holder is garbage. A head added after one was removed then runs on the removed
head's streams, in a thread that most likely got its cuBLAS handle too, and cuBLAS finds the workspaces it left;
the number of workspaces is bounded by the streams and threads alive at once, not by how often heads come and go.
Work the old holder left queued on a stream runs before the new holder's, in stream order, which is harmless.
"""

from __future__ import annotations

import collections
import weakref
from collections.abc import Callable
from typing import Any

import torch

# (device index, priority) -> streams whose holders are gone. A deque: its append and pop are atomic, so a holder's
# finalizer, which may run in any thread in the middle of anything (a garbage collection), needs no lock.
_free: dict[tuple[int, int], collections.deque[Any]] = collections.defaultdict(collections.deque)


def lend(
    holder: object, device: torch.device, priority: int = 0, new: Callable[[], Any] | None = None
) -> torch.cuda.Stream:
    """A stream on CUDA ``device`` at ``priority`` (torch's: lower is more urgent) for ``holder``, given back to the
    next caller once ``holder`` is garbage (Note [Reused streams]). ``new`` makes a stream when none is free
    (default: ``torch.cuda.Stream``)."""
    key = (device.index if device.index is not None else torch.cuda.current_device(), priority)
    free = _free[key]
    try:
        stream = free.pop()
    except IndexError:
        stream = new() if new is not None else torch.cuda.Stream(device, priority=priority)
    weakref.finalize(holder, free.append, stream)
    return stream
