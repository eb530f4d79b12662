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
lock, which is why it is off by default.

The caller's hop is the same: ``Engine.wait`` sleeps on the control block's output word until a head publishes, and
the last head's result reaches the caller a wake-up later. ``runtime.wait_spin_us`` > 0 applies the same prediction
there (``SpinWindow``): the caller sleeps through the part of the wait its recent waits predict (woken early by any
head that publishes meanwhile), then polls the output word for at most twice the window.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

import torch


class SpinWindow:
    """When to stop sleeping and start polling in a wait whose length recent waits predict (Note [Device sync]).

    ``poll_from(t0)``: the time a wait that began at ``t0`` starts polling; ``give_up(t)``: polling that began at
    ``t`` stops then and sleeps again; ``learn(took)`` folds a finished wait's length into the prediction (a moving
    average). ``spin_s`` 0: never polls.
    """

    __slots__ = ("expected_s", "spin_s")

    def __init__(self, spin_s: float = 0.0) -> None:
        self.spin_s = spin_s
        self.expected_s = 0.0

    def poll_from(self, t0: float) -> float:
        return t0 + self.expected_s - self.spin_s

    def give_up(self, t: float) -> float:
        return t + 2 * self.spin_s

    def learn(self, took: float) -> None:
        self.expected_s += 0.125 * (took - self.expected_s)


class DeviceContext:
    def __init__(self, device: torch.device | str, priority: int = 0, spin_s: float = 0.0) -> None:
        self.device = torch.device(device)
        self.spin = SpinWindow(spin_s)  # how complete() waits
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
        event, spin = self.event, self.spin
        event.record(self.stream)
        if spin.spin_s <= 0:
            event.synchronize()
            return
        t0 = time.monotonic()
        ahead = spin.poll_from(t0) - t0
        if ahead > 0:
            time.sleep(ahead)
        give_up = spin.give_up(time.monotonic())
        while not event.query():
            if time.monotonic() > give_up:
                event.synchronize()
                break
            time.sleep(0)  # lets the other workers' threads have the interpreter lock between polls
        spin.learn(time.monotonic() - t0)

    def memory_bytes(self) -> int:
        """Device memory this process holds through PyTorch's allocator (reserved), 0 on the CPU."""
        if not self.cuda:
            return 0
        return int(torch.cuda.memory_reserved(self.device))
