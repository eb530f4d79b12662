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

Note [Stream priority at run time]
~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~
A worker's stream has a CUDA priority by its model's priority (runtime/priority.py ``stream_levels``), which the
device uses to pick between the queued work of models that share a context. A stream's priority is fixed when it is
made, so a priority changed at run time (``Engine.set_priority``) cannot change it; the worker moves instead. The
governor writes each model's level into the control block at start, on every change and before an added head's
worker starts, so a worker starts at its level (a restart too, after changes). Before each run, at most every
``RESTREAM_S``, the worker reads its level; at a new one it takes a stream of that priority (lent, Note [Reused
streams] in backends/streams.py; kept for a return to that level), orders it after everything queued on the old one,
on the device, and makes it current. Never while the submitting thread may launch for it: it launches on
``stream`` only while the worker is armed (Note [Inline launch] in handoff.py), and the worker moves only in its own
thread, unarmed. CUDA graphs replay on any stream; events mark and wait on whichever is current. A model with a
context to itself (a process of its own, no MPS) never moves: there its stream's priority ranks it against nothing.
What a move costs: an eager model's first runs on the new stream allocate its activations afresh (the caching
allocator keeps blocks per stream) and cuBLAS a workspace for the stream (32 MiB on Hopper), once per level it
visits. ONNX Runtime keeps the stream it was created with (its executor orders it with the current one). Measured
(H200, thread mode, 12 cameras over what the GPU serves): the raised model's latency tail is shorter
(docs/benchmarks.md).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

from vpengine.backends.streams import lend

RESTREAM_S = 0.05  # how often a worker looks at its stream level: a priority change reaches the device this soon


class DeviceContext:
    def __init__(self, device: torch.device | str, priority: int = 0) -> None:
        """``priority``: steps above the default CUDA stream priority (more urgent; torch clamps it to the
        priorities its stream pools have; runtime/priority.py ``stream_levels``)."""
        self.device = torch.device(device)
        self.cuda = self.device.type == "cuda"
        if self.cuda:
            if self.device.index is None:  # "cuda" and "cuda:0" must compare equal to the rings' devices
                self.device = torch.device("cuda", torch.cuda.current_device())
            torch.cuda.set_device(self.device)
            # CUDA: lower numbers are more urgent. Lent, not new: Note [Reused streams] in backends/streams.py.
            self.stream: torch.cuda.Stream | None = lend(self, self.device, -priority)
            self._streams = {priority: self.stream}
            self.event: torch.cuda.Event | None = torch.cuda.Event(blocking=True)
        else:
            self.stream = None
            self.event = None
        self.level = priority
        self.moves = True  # whether ``use_level`` moves (Note [Stream priority at run time])

    def use_level(self, level: int) -> bool:
        """Run later work on a stream ``level`` steps above the default priority (Note [Stream priority at run
        time]), ordered after all work queued so far on the current one, and current from now on; whether the
        stream changed. Only between runs, by the worker's own thread, inside ``active()`` (which puts back, when it
        ends, the stream that was current before it)."""
        if self.stream is None or not self.moves or level == self.level:
            return False
        stream = self._streams.get(level)
        if stream is None:
            stream = self._streams[level] = lend(self, self.device, -level)
        stream.wait_stream(self.stream)  # on the device: no host wait
        self.stream, self.level = stream, level
        torch.cuda.set_stream(stream)
        return True

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
