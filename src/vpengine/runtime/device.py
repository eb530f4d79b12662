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
        self.expected_s = 0.0  # moving average of how long complete() waited
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
        polling the last stretch when ``spin_s`` > 0 (Note [Device sync])."""
        if self.stream is None or self.event is None:
            return
        event = self.event
        event.record(self.stream)
        if self.spin_s <= 0:
            event.synchronize()
            return
        t0 = time.monotonic()
        ahead = self.expected_s - self.spin_s
        if ahead > 0:
            time.sleep(ahead)
        give_up = time.monotonic() + 2 * self.spin_s
        while not event.query():
            if time.monotonic() > give_up:
                event.synchronize()
                break
            time.sleep(0)  # lets the other workers' threads have the interpreter lock between polls
        self.expected_s += 0.125 * (time.monotonic() - t0 - self.expected_s)

    def memory_bytes(self) -> int:
        """Device memory this process holds through PyTorch's allocator (reserved), 0 on the CPU."""
        if not self.cuda:
            return 0
        return int(torch.cuda.memory_reserved(self.device))
