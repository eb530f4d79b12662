"""Per-worker device context: its own CUDA stream and a blocking event for the sync rules.

Note [Device sync]
~~~~~~~~~~~~~~~~~~
Device work is asynchronous, so "the work that filled a slot" and "the work that read it" are not finished when
the Python call returns. A worker therefore records an event on its stream after the model ran and the outputs
were copied into the output slot, waits for it, and only then publishes the output slot and releases the input
slot. The event is created with ``blocking=True`` (cudaEventBlockingSync) so the waiting thread sleeps in the
driver instead of spinning a CPU core at 100%. On the CPU, PyTorch ops are synchronous and ``complete`` is a no-op.
One hop orders on the device instead: the foundation's features to the heads in thread mode on CUDA, where the heads'
streams wait on an event per slot (``wait_on``/``mark``, Note [Event hand-off] in worker.py).

Waking from that sleep takes 0.1-0.2 ms (measured on an H100 VM), once per model per frame, on the critical path of
every frame. ``runtime.sync_spin_us`` > 0 trades a little CPU for it: the worker sleeps (``time.sleep``, GIL released)
through the part of the work its recent runs predict, minus the spin window, then polls the event, yielding the
interpreter lock between polls, for at most twice the window, and falls back to the sleeping wait after that. The
prediction is a moving average of how long the waits took. No work in flight, no polling: idle workers still sleep.
On an H100 (thread mode, compiled backbone + depth + seg) a 200 us window took a frame from 4.16 to 3.98 ms; with eight
depth heads in thread mode it made things worse (7.4 -> 8.3 ms), the polling threads contending for the interpreter
lock, which is why it is off by default. The same prediction was tried for the caller's wait in ``Engine.wait``
(commit 44ac87f, reverted): no gain alone (3.57 vs 3.58 ms), and with this spin on too the floor's thread-mode frame
went from 3.4 to 4.4 ms: a thread polling with ``time.sleep(0)`` retakes the interpreter lock before a woken thread
gets it, and that one asks for it only after the 5 ms switch interval (benchmarks/results/h100/profile_steps_wait.json).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

import torch


class DeviceContext:
    def __init__(self, device: torch.device | str, priority: int = 0, spin_s: float = 0.0) -> None:
        self.device = torch.device(device)
        self.spin_s = spin_s
        self.expected_s = 0.0  # moving average of how long complete() waited; 0: not known (yet, or any more)
        self._marked: torch.cuda.Event | None = None  # the event mark_done recorded last
        self.cuda = self.device.type == "cuda"
        if self.cuda:
            if self.device.index is None:  # "cuda" and "cuda:0" must compare equal to the rings' devices
                self.device = torch.device("cuda", torch.cuda.current_device())
            torch.cuda.set_device(self.device)
            # CUDA: a lower number is a higher priority. PyTorch maps a priority above what the device (or its own
            # stream pool) has to the highest there is; ``priority`` says what the stream got.
            self.stream: torch.cuda.Stream | None = torch.cuda.Stream(self.device, priority=priority)
            self.event: torch.cuda.Event | None = torch.cuda.Event(blocking=True)
            # default flags: its synchronize() polls in the driver (cudaDeviceScheduleAuto spins with a core each)
            self.spin_event: torch.cuda.Event | None = torch.cuda.Event() if spin_s > 0 else None
        else:
            self.stream = None
            self.event = self.spin_event = None

    @contextlib.contextmanager
    def active(self) -> Iterator[None]:
        if self.stream is not None:
            with torch.cuda.stream(self.stream):
                yield
        else:
            yield

    def wait_on(self, event: torch.cuda.Event) -> None:
        """Order this worker's later device work after ``event`` (Note [Event hand-off]); no host wait."""
        if self.stream is not None:
            self.stream.wait_event(event)

    def mark(self, event: torch.cuda.Event) -> None:
        """Record ``event`` after all work queued so far on this worker's stream."""
        if self.stream is not None:
            event.record(self.stream)

    def complete(self) -> None:
        """Block until all work queued so far on this worker's stream has finished: sleeping, or sleeping and then
        spinning in the driver for the last stretch when ``spin_s`` > 0 (Note [Device sync])."""
        if self.stream is None or self.event is None:
            return
        self.wait_marked(self.mark_done())

    def mark_done(self) -> float:
        """Record the event that ``wait_marked`` waits on, after all work queued so far on this worker's stream.
        Returns when (``time.monotonic``). The wait may happen in another thread (Note [Inline finish])."""
        if self.stream is None or self.event is None:
            return time.monotonic()
        spin = self.spin_event
        # a spin needs a prediction: without one (not learnt yet, or the last spin outlasted its window) it sleeps
        self._marked = spin if spin is not None and self.expected_s > 0 else self.event
        self._marked.record(self.stream)
        return time.monotonic()

    def wait_marked(self, t_marked: float) -> None:
        """Block until the work before ``mark_done``'s event (recorded at ``t_marked``) has finished."""
        marked = self._marked
        if self.stream is None or marked is None:
            return
        if marked is self.event:
            marked.synchronize()
            if self.spin_event is not None:  # learning what a run takes, from a wait that does not spin
                self.expected_s = time.monotonic() - t_marked
            return
        ahead = t_marked + self.expected_s - self.spin_s - time.monotonic()
        if ahead > 0:
            time.sleep(ahead)
        marked.synchronize()  # the driver polls the device; the interpreter lock is free meanwhile
        waited = time.monotonic() - t_marked
        if waited > self.expected_s + 2 * self.spin_s:
            self.expected_s = 0.0  # spun for longer than the window: the next run sleeps and learns anew
        else:
            self.expected_s += 0.125 * (waited - self.expected_s)

    @property
    def priority(self) -> int:
        """The stream's priority as the device has it (0 on the CPU)."""
        return int(self.stream.priority) if self.stream is not None else 0

    def memory_bytes(self) -> int:
        """Device memory this process holds through PyTorch's allocator (reserved), 0 on the CPU."""
        if not self.cuda:
            return 0
        return int(torch.cuda.memory_reserved(self.device))
