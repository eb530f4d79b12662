"""Per-worker device context: its own CUDA stream and a blocking event for the sync rules.

Note [Device sync]
~~~~~~~~~~~~~~~~~~
Device work is asynchronous, so "the work that filled a slot" and "the work that read it" are not finished when
the Python call returns. A worker therefore records an event on its stream after the model ran and the outputs
were copied into the output slot, waits for it, and only then publishes the output slot and releases the input
slot. The event is created with ``blocking=True`` (cudaEventBlockingSync) so the waiting thread sleeps in the
driver instead of spinning a CPU core at 100%. On the CPU, PyTorch ops are synchronous and ``complete`` is a no-op.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


class DeviceContext:
    def __init__(self, device: torch.device | str, priority: int = 0) -> None:
        self.device = torch.device(device)
        self.cuda = self.device.type == "cuda"
        if self.cuda:
            if self.device.index is None:  # "cuda" and "cuda:0" must compare equal to the rings' devices
                self.device = torch.device("cuda", torch.cuda.current_device())
            torch.cuda.set_device(self.device)
            lo, hi = (
                torch.cuda.get_stream_priority_range()
                if hasattr(torch.cuda, "get_stream_priority_range")
                else (0, 0)
            )
            prio = max(min(priority, lo), hi)  # CUDA: lower number = higher priority; clamp into the range
            self.stream: torch.cuda.Stream | None = torch.cuda.Stream(self.device, priority=prio)
            self.event: torch.cuda.Event | None = torch.cuda.Event(blocking=True)
        else:
            self.stream = None
            self.event = None

    @contextlib.contextmanager
    def active(self) -> Iterator[None]:
        if self.stream is not None:
            with torch.cuda.stream(self.stream):
                yield
        else:
            yield

    def complete(self) -> None:
        """Block (sleeping, not spinning) until all work queued so far on this worker's stream has finished."""
        if self.stream is not None and self.event is not None:
            self.event.record(self.stream)
            self.event.synchronize()

    def memory_bytes(self) -> int:
        """Device memory this process holds through PyTorch's allocator (reserved), 0 on the CPU."""
        if not self.cuda:
            return 0
        return int(torch.cuda.memory_reserved(self.device))
