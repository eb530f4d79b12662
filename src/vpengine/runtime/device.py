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
through the part of the work its recent runs predict, minus the spin window, then waits on a second event, made with
default flags, whose ``synchronize`` polls the device in the driver with the interpreter lock released. (The first
version polled from Python and yielded the lock between polls; other threads then waited for it.) The prediction is a
moving average of the waits, learnt from a sleeping one; a driver spin cannot be cut short, so a run slower than
predicted is spun through, and a spin that outlasts twice its window makes the next run sleep and learn anew. No work
in flight, no spinning: idle workers still sleep. Measured on an H100 (thread mode, compiled depth + seg, frame slot):
a 200 us window took a frame from 3.43-3.48 to 3.32 ms p50, as fast as spinning through the whole wait (3.31 ms;
profile_steps_driver_spin.json); the floor run gave 3.40 -> 3.35 ms p50 with a worse mean; with eight depth heads it
still made things worse (6.2-6.7 -> 7.2 ms p50), which is why it is off by default.

Two ways to shorten the caller's side were tried and reverted. The same prediction for the caller's wait in
``Engine.wait`` (commit 44ac87f): no gain alone (3.57 vs 3.58 ms), and with the workers' Python polling on too the
floor's thread-mode frame went from 3.4 to 4.4 ms: a thread polling with ``time.sleep(0)`` retakes the interpreter
lock before a woken thread gets it, and that one asks for it only after the 5 ms switch interval
(benchmarks/results/h100/profile_steps_wait.json). And "inline finish" (commit a6cc1be): a head handed its queued run
of a frame to the thread waiting for that frame, which waited for the device work and published the output itself,
so that the head's thread no longer had to wake it. On the floor that was slower, 3.51 against 3.29 ms p50 on one
machine (paper_cuda_floor_inline_finish_*.json); one likely reason is that the waiting thread then publishes both
heads after the last is done, where the heads' threads publish the first while the second still runs.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

import torch


class DeviceContext:
    def __init__(self, device: torch.device | str, priority: int = 0, spin_s: float = 0.0) -> None:
        self.device = torch.device(device)
        self.cuda = self.device.type == "cuda"
        if self.cuda:
            if self.device.index is None:  # "cuda" and "cuda:0" must compare equal to the rings' devices
                self.device = torch.device("cuda", torch.cuda.current_device())
            torch.cuda.set_device(self.device)
            # CUDA: a lower number is a higher priority. PyTorch maps a priority above what the device (or its own
            # stream pool) has to the highest there is; ``priority`` says what the stream got.
            self.stream: torch.cuda.Stream | None = torch.cuda.Stream(self.device, priority=priority)
            self.event: torch.cuda.Event | None = torch.cuda.Event(blocking=True)
        else:
            self.stream = None
            self.event = None
        self.set_spin(spin_s)

    def set_spin(self, spin_s: float) -> None:
        """The spin window of ``complete`` (``runtime.sync_spin_us``, in seconds; 0: sleep only). Forgets what it
        had learnt of the runs' times."""
        self.spin_s = spin_s
        self.expected_s = 0.0  # moving average of how long complete() waited; 0: not known (yet, or any more)
        # default flags: its synchronize() polls in the driver (cudaDeviceScheduleAuto spins with a core each)
        self.spin_event: torch.cuda.Event | None = torch.cuda.Event() if spin_s > 0 and self.cuda else None

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
        t0 = time.monotonic()
        spin = self.spin_event
        if spin is None or self.expected_s <= 0:
            self.event.record(self.stream)
            self.event.synchronize()
            if spin is not None:  # learning what a run takes, from a wait that does not spin
                self.expected_s = time.monotonic() - t0
            return
        spin.record(self.stream)
        ahead = self.expected_s - self.spin_s
        if ahead > 0:
            time.sleep(ahead)
        spin.synchronize()  # the driver polls the device; the interpreter lock is free meanwhile
        waited = time.monotonic() - t0
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
