"""Per-worker device context: its own CUDA stream and a blocking event for the sync rules.

Note [Device sync]
~~~~~~~~~~~~~~~~~~
Device work is asynchronous, so "the work that filled a slot" and "the work that read it" are not finished when
the Python call returns. A worker therefore records an event on its stream after the model ran and the outputs
were copied into the output slot, waits for it, and only then publishes the output slot and releases the input
slot. The event is created with ``blocking=True`` (cudaEventBlockingSync) so the waiting thread sleeps in the
driver instead of spinning a CPU core at 100%. On the CPU, PyTorch ops are synchronous and ``complete`` is a no-op.
In thread mode on CUDA the hops between models are ordered on the device instead (``wait_on``/``mark``, Notes [Event
hand-off] and [Result hand-off] in handoff.py); a worker still waits for its own work before it releases its input.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

from vpengine.backends.streams import lend


class DeviceContext:
    def __init__(self, device: torch.device | str, priority: int = 0) -> None:
        """``priority``: steps above the default CUDA stream priority (more urgent; clamped to what the device
        has; runtime/priority.py ``stream_level``)."""
        self.device = torch.device(device)
        self.cuda = self.device.type == "cuda"
        if self.cuda:
            if self.device.index is None:  # "cuda" and "cuda:0" must compare equal to the rings' devices
                self.device = torch.device("cuda", torch.cuda.current_device())
            torch.cuda.set_device(self.device)
            # CUDA: lower numbers are more urgent. Lent, not new: Note [Reused streams] in backends/streams.py.
            self.stream: torch.cuda.Stream | None = lend(self, self.device, -priority)
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

    def wait_on(self, event: torch.cuda.Event) -> None:
        """Order this worker's later device work after ``event``; no host wait."""
        if self.stream is not None:
            self.stream.wait_event(event)

    def mark(self, event: torch.cuda.Event) -> None:
        """Record ``event`` after all work queued so far on this worker's stream."""
        if self.stream is not None:
            event.record(self.stream)

    def complete(self) -> None:
        """Block, asleep in the driver, until all work queued so far on this worker's stream has finished."""
        if self.stream is None or self.event is None:
            return
        self.event.record(self.stream)
        self.event.synchronize()

    def memory_bytes(self) -> int:
        """Device memory this process holds through PyTorch's allocator (reserved), 0 on the CPU."""
        if not self.cuda:
            return 0
        return int(torch.cuda.memory_reserved(self.device))
