"""Hand-offs between the threads of one process (thread mode on CUDA): device work handed on queued, not done.

The engine owns them (:func:`make_handoffs`, at start) and gives each worker the ones it takes part in
(:meth:`Handoffs.for_worker`); the rings stay plain mailboxes. Process mode and the CPU have none: there every
writer publishes only completed work (Note [Device sync] in device.py). Measurements behind these choices are in
docs/benchmarks.md.

Note [Event hand-off]
~~~~~~~~~~~~~~~~~~~~~
Waiting on the host for the foundation's work, then waking each head to queue its own, costs two wake-ups per frame
on the critical path while the GPU idles. So the foundation worker records a CUDA event per feature slot right after
queueing its work and publishes the slot at once; a head that pins the slot makes its stream wait on that event
(``cudaStreamWaitEvent``, no host wait) before it reads. Invariant: no head's device work reads a slot before the
work that filled it is complete (stream order), and the foundation still waits for its own work before it releases
its input slot, so the caller's frame is never overwritten while it is read. Its run is counted when published and
its times corrected once the work is done (``ControlBlock.amend_last_run``).

Note [Result hand-off]
~~~~~~~~~~~~~~~~~~~~~~
Likewise a head records a blocking event per output slot after queueing its work and the copy to the host,
publishes at once and wakes the caller, who pins the result while the device still computes it and waits on the
event (:meth:`SlotEvents.wait_done`): the wake-ups happen while the device works, not after. Invariants: no reader
reads a slot's content before ``wait_done`` says it is there (arrays over it may be made before: borrowing reads
nothing); ``Engine.results``/``latest`` take only slots whose work is done (the ring's pin filter
:meth:`SlotEvents.done`), so they never block on the device and a FIFO reader never takes a result out of order;
the head still waits for its work before releasing its input slot and records when it was done (each result's
latency), then wakes readers again. A wait in the driver cannot be cut short, so ``Engine.wait`` waits there only
for a result its head's recent results say will be done before the caller's timeout (:meth:`SlotEvents.done_after`).

The caller's wait sleeps through the part of the work that the head's recent results predict, then polls the event
until at most a window past the predicted end (``WAIT_SPIN_S`` plus twice the results' recent spread, at most three
times ``WAIT_SPIN_S``), offering the interpreter lock between polls with ``os.sched_yield`` (``time.sleep(0)`` would
sleep out the timer slack), then sleeps in the driver: its CPU is bounded however late a head is, and it never spins
while idle. Before waiting, ``Engine.wait`` borrows every result it pinned, so little is left to do once the last one
is there.

Note [Inline launch]
~~~~~~~~~~~~~~~~~~~~
The frame's own hop costs a wake-up too. When the foundation runs from graphs bound to the slots on CUDA, its worker,
ready for a frame and unlimited, *arms* the input ring's :class:`InlineLaunch` with its output slot and a launch
callable; the thread that publishes the next frame (``Engine.submit`` or a ``frame_slot`` closing) queues the
foundation's work itself, on the foundation's stream, *before* publishing the frame (the slot is still its writer's:
nobody else can see it), then publishes it already pinned for the foundation's reader (``publish_pinned``) and hands
the pinned slots to the worker, which finishes the run as usual. Invariants: arming, disarming, taking a frame from
the ring and the launch all happen under the offer's lock, so each frame is taken exactly once; the worker alone
decides when it is ready; a rate-limited worker never arms (its gate needs each frame's stamp first); a launch that
raises is handed to the worker, which fails that frame (Note [Frame errors] in worker.py); ``Engine.set_rate``
stores the rate, then takes the lock, so no frame submitted after it returns runs under the old rate.

Note [Launch path]
~~~~~~~~~~~~~~~~~~
Host code runs several times slower right after its thread waited, and every run begins that way. So a worker's
loop makes its stream current and turns inference mode on once for its whole life (the stream again only when a
priority change moves it, Note [Stream priority at run time] in device.py), and a slot-bound executor
launched from the submitting thread launches its graphs with ``cudaGraphLaunch`` straight onto the worker's stream
(``run_bound_on``), needing no stream switch and no inference mode.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from vpengine.transport.ring import RingReader, RingWriter, SlotInfo, SlotRing

#: How far past a result's predicted end the caller polls before sleeping in the driver (Note [Result hand-off]).
WAIT_SPIN_S = 200e-6


class SlotEvents:
    """Note [Event hand-off] / [Result hand-off]: one CUDA event per slot of a ring whose writer publishes queued
    work, when each slot's work was seen done, and how long that usually takes after the publish.

    ``make_event(blocking=...)`` builds the events (tests pass stand-ins). Used by the ring's one writer thread
    (``record``, ``mark_done``) and the engine's readers (under its read lock)."""

    def __init__(self, n_slots: int, blocking: bool, make_event: Callable[..., Any] | None = None) -> None:
        if make_event is None:
            import torch

            make_event = torch.cuda.Event
        self.events = [make_event(blocking=blocking) for _ in range(n_slots)]
        # per slot: (seq, monotonic time) of the last publish whose work was seen done
        self.done_at: list[tuple[int, float]] = [(0, 0.0)] * n_slots
        # moving average of the time from publish to done, and of how far each was from it (its spread)
        self.publish_to_done_s = 0.0
        self.publish_to_done_dev_s = 0.0

    def done(self, index: int, seq: int) -> bool:
        """Whether published slot ``index`` (sequence ``seq``) holds its content now; the rings' pin filter."""
        return self.done_at[index][0] == seq or bool(self.events[index].query())

    def mark_done(self, ring: SlotRing, slot: SlotInfo, t_done: float) -> None:
        """The writer saw the work behind its published ``slot`` finish at ``t_done``: record it and wake the ring's
        readers waiting for a done slot."""
        self.record_done(slot, t_done)
        ring.notify_readers()

    def record_done(self, slot: SlotInfo, t_done: float) -> None:
        """The first to see a slot's work done (its writer, or a reader waiting for it) says when; each slot's time
        from publish to done feeds the estimate ``wait_done`` predicts with (as TCP's round-trip estimate: the mean,
        gain 1/8, and the mean deviation from it, gain 1/4)."""
        if self.done_at[slot.index][0] == slot.seq:
            return
        self.done_at[slot.index] = (slot.seq, t_done)
        took = t_done - slot.t_publish
        ema = self.publish_to_done_s
        if ema <= 0:
            self.publish_to_done_s = took
            return
        error = took - ema
        self.publish_to_done_s = ema + 0.125 * error
        self.publish_to_done_dev_s += 0.25 * (abs(error) - self.publish_to_done_dev_s)

    def done_after(self, slot: SlotInfo, deadline: float) -> bool:
        """Whether pinned ``slot``'s work is expected to finish only after ``deadline`` (monotonic seconds): never if
        it is done; else by its publish time plus the usual publish-to-done time (none seen yet: at once)."""
        if self.done(slot.index, slot.seq):
            return False
        return slot.t_publish + self.publish_to_done_s > deadline

    def wait_done(self, slot: SlotInfo, spin_s: float | None = None) -> float:
        """Block until pinned ``slot``'s content is there; returns when it was (monotonic seconds): when its writer
        or this call saw its work finish, whichever came first. ``spin_s`` > 0: sleep through the predicted part,
        then poll until at most the window past the predicted end, then sleep in the driver (Note [Result
        hand-off]); 0: the event's own wait, asleep in the driver; None: ``WAIT_SPIN_S``."""
        spin_s = WAIT_SPIN_S if spin_s is None else spin_s
        seq, t_done = self.done_at[slot.index]
        if seq == slot.seq:
            return t_done
        event = self.events[slot.index]
        if event.query():
            return time.monotonic()
        predicted = self.publish_to_done_s  # 0: nothing learnt yet
        window = spin_s + min(2 * self.publish_to_done_dev_s, 2 * spin_s)
        if not (spin_s > 0 and predicted > 0 and poll(event, slot, predicted, window)):
            event.synchronize()
        t_done = time.monotonic()
        self.record_done(slot, t_done)
        return t_done


def poll(
    event: Any, slot: SlotInfo, predicted_s: float, window_s: float, offer: Callable[[], Any] = os.sched_yield
) -> bool:
    """``wait_done``'s spin: sleep until ``window_s`` before ``slot``'s predicted end, then poll ``event`` until it
    is done (True) or ``window_s`` past that end has come (False), calling ``offer`` between polls."""
    due = slot.t_publish + predicted_s
    now = time.monotonic()
    if due - window_s > now:
        time.sleep(due - window_s - now)
        now = time.monotonic()
    until = max(due, now) + window_s
    while not event.query():
        if time.monotonic() >= until:
            return False
        # os.sched_yield gives the interpreter lock to a thread that wants it (a head publishing), at once;
        # time.sleep(0) would too, but sleeps out the timer slack (about 55 us on Linux)
        offer()
    return True


class InlineLaunch:
    """Note [Inline launch]: the offer from a ready foundation worker to the thread that publishes the next frame.
    One per engine (thread mode), kept across restarts of the worker."""

    def __init__(self) -> None:
        self.cond = threading.Condition(threading.Lock())
        self._launch: Callable[[SlotInfo], None] | None = None
        self._reader: RingReader | None = None
        self._allowed: Callable[[], bool] | None = None
        self._done: tuple[SlotInfo, float, BaseException | None] | None = None
        self.launches = 0  # frames launched by submitting threads

    # worker side, holding cond
    def arm(self, launch: Callable[[SlotInfo], None], reader: RingReader, allowed: Callable[[], bool]) -> None:
        """Offer ``launch`` (queue the worker's work on a frame's slot, into the output slot it holds) to the next
        frame's publisher, who publishes the frame pinned for ``reader``; ``allowed`` says, at that moment, whether
        the worker may still take it (a rate set since it armed: no)."""
        self._launch, self._reader, self._allowed = launch, reader, allowed

    def disarm(self) -> None:
        self._launch = self._reader = self._allowed = None

    def take_done(self) -> tuple[SlotInfo, float, BaseException | None] | None:
        """The frame launched while armed: (its slot, pinned for the worker; when; the launch's error), or None."""
        done, self._done = self._done, None
        return done

    # submitting side
    def publish(
        self, writer: RingWriter, slot: SlotInfo, frame_id: int, t_capture: float, t_submit: float, tag: int = 0
    ) -> int:
        """Publish the frame filled in ``slot`` (the input ring's ``writer`` holds it); if a worker is armed, queue
        its work on the frame first, then publish the frame pinned for its reader and hand it over. The frame's seq.
        """
        with self.cond:
            launch, reader, allowed = self._launch, self._reader, self._allowed
            if launch is None or reader is None or allowed is None or not allowed():
                # no worker armed, or a rate set since (a pause, say): the worker's gate decides, once woken
                return writer.publish(slot, frame_id, t_capture, t_submit, tag=tag)
            self.disarm()
            t_start = time.monotonic()
            error: BaseException | None = None
            try:  # queued before the frame is published: nobody else can see the slot yet, let alone reuse it
                launch(slot)
            except Exception as e:  # the worker's to handle (Note [Frame errors] in worker.py); never raised in submit
                error = e
            pinned = writer.publish_pinned(slot, frame_id, t_capture, t_submit, reader, tag)
            self._done = (pinned, t_start, error)
            self.launches += 1
            self.cond.notify_all()
            return pinned.seq

    def wake(self) -> None:
        """Wake an armed worker (a rate change, stop), which then disarms."""
        with self.cond:
            self.cond.notify_all()


def inline_wanted(cuda: bool, bound: bool) -> bool:
    """Whether a foundation worker takes frames through the offer (Note [Inline launch]): on CUDA, from graphs
    bound to the slots, where a launch is three graph launches and costs the submitting thread little."""
    return cuda and bound


@dataclass
class WorkerHandoff:
    """What one worker takes part in: the events of its input ring (it waits on them before reading), of its output
    ring (it records them instead of waiting before publishing), and the offer (the foundation)."""

    in_events: SlotEvents | None = None
    out_events: SlotEvents | None = None
    inline: InlineLaunch | None = None


@dataclass
class Handoffs:
    """Every hand-off of an engine in thread mode: the features' events, each head's results' events (CUDA only),
    and the input ring's offer."""

    features: SlotEvents | None = None
    results: dict[str, SlotEvents] = field(default_factory=dict)
    inline: InlineLaunch | None = None

    def add_head(self, name: str, out_ring: SlotRing) -> None:
        """The hand-off of a head added at run time: its results' events, where the others have them (CUDA)."""
        if self.features is not None:
            self.results[name] = SlotEvents(out_ring.n_slots, blocking=True)

    def remove_head(self, name: str) -> None:
        self.results.pop(name, None)

    def for_worker(self, name: str) -> WorkerHandoff:
        if name == "foundation":
            return WorkerHandoff(None, self.features, self.inline)
        return WorkerHandoff(self.features, self.results.get(name), None)


def make_handoffs(rings: dict[str, SlotRing], heads: list[str], cuda: bool) -> Handoffs:
    """The hand-offs of a thread-mode engine whose mailboxes are ``rings`` (``features``, ``out.<head>``)."""
    if not cuda:
        return Handoffs(inline=InlineLaunch())
    return Handoffs(
        # the heads' streams wait on these on the device; nobody waits on them on the host
        features=SlotEvents(rings["features"].n_slots, blocking=False),
        # the caller sleeps in the driver on these at the end of a wait
        results={h: SlotEvents(rings[f"out.{h}"].n_slots, blocking=True) for h in heads},
        inline=InlineLaunch(),
    )
