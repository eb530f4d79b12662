"""Note [Result hand-off]: a head publishes results whose device work is still queued, with one event per slot.
Here stand-in events say when that work is done (a real one needs a GPU: tests/gpu/test_event_handoff_cuda.py runs
the engine both ways). What must hold: a reader that asks for done results never gets a queued one, nor one out of
order; ``wait_done`` never returns before the work is done; the writer's wake-up reaches readers waiting for done
results; a result's time is when its work was done."""

from __future__ import annotations

import statistics
import sys
import threading
import time

import pytest
import torch

from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine
from vpengine.runtime.handoff import SlotEvents
from vpengine.specs import TensorSpec
from vpengine.transport import ring as ring_module
from vpengine.transport.ring import SlotRing, fifo_queue, latest_buffer

SPECS = {"x": TensorSpec((4,), "float32")}


class Event:
    """A slot's event: done once the 'device' finished; ``synchronize`` is that wait (here: the work finishes)."""

    def __init__(self) -> None:
        self.done = True  # a CUDA event never recorded reports done
        self.syncs = 0

    def record(self) -> None:
        self.done = False

    def query(self) -> bool:
        return self.done

    def synchronize(self) -> None:
        self.syncs += 1
        self.synced_at = time.monotonic()
        self.done = True


def handed_off(ring: SlotRing) -> SlotEvents:
    """The ring's events as the engine makes them for a head's results (runtime/handoff.py), stand-ins here."""
    return SlotEvents(ring.n_slots, blocking=True, make_event=lambda blocking: Event())


def publish_queued(ring: SlotRing, ev: SlotEvents, value: float) -> tuple[int, int]:
    """What a head does: queue the work into a slot, record its event, publish at once. (slot index, seq)."""
    w = ring.writer()
    slot = w.acquire(timeout=0)
    assert slot is not None
    slot.tensors["x"].fill_(value)
    ev.events[slot.index].record()
    seq = w.publish(slot, int(value), 0.0, time.monotonic())
    return slot.index, seq


def finish(ring: SlotRing, ev: SlotEvents, index: int, seq: int) -> float:
    """The device finished the slot's work and its writer saw it."""
    ev.events[index].done = True
    t = time.monotonic()
    slot = ring._slot_info(index, tensors=False)
    assert slot.seq == seq
    ev.mark_done(ring, slot, t)
    return t


@pytest.mark.parametrize("make", [latest_buffer, lambda *a: fifo_queue(*a, n_slots=4)], ids=["latest", "fifo"])
def test_a_reader_asking_for_done_results_does_not_take_queued_ones_and_takes_them_once_done(make):
    ring = make("out", SPECS, ["results"])
    try:
        ev = handed_off(ring)
        r = ring.reader("results")
        _, seq = publish_queued(ring, ev, 1.0)
        assert r.pin(accept=ev.done) is None  # queued: not there yet, and not consumed either
        assert r.cursor == 0
        slot = r.pin()  # a reader that orders on the device (a head reading features) takes it at once
        assert slot is not None and slot.seq == seq
        r.release(slot)
        i2, seq2 = publish_queued(ring, ev, 2.0)
        assert r.pin(accept=ev.done) is None
        finish(ring, ev, i2, seq2)
        slot = r.pin(accept=ev.done)
        assert slot is not None and slot.seq == seq2 and slot.tensors["x"][0].item() == 2.0
        r.release(slot)
    finally:
        ring.close()


def test_a_fifo_reader_asking_for_done_results_never_takes_one_out_of_order():
    ring = fifo_queue("out", SPECS, ["results"], n_slots=4)
    try:
        ev = handed_off(ring)
        r = ring.reader("results")
        a = publish_queued(ring, ev, 1.0)
        b = publish_queued(ring, ev, 2.0)
        finish(ring, ev, *b)  # the later one is done first
        assert r.pin(accept=ev.done) is None
        finish(ring, ev, *a)
        got = []
        while (s := r.pin(accept=ev.done)) is not None:
            got.append(s.seq)
            r.release(s)
        assert got == [a[1], b[1]]
    finally:
        ring.close()


def test_a_done_peek_takes_the_newest_done_result_not_a_queued_newer_one():
    ring = latest_buffer("out", SPECS, ["peek"])
    try:
        ev = handed_off(ring)
        r = ring.reader("peek")
        assert r.pin(peek=True, accept=ev.done) is None
        a = publish_queued(ring, ev, 1.0)
        finish(ring, ev, *a)
        publish_queued(ring, ev, 2.0)
        slot = r.pin(peek=True, accept=ev.done)
        assert slot is not None and slot.seq == a[1] and slot.tensors["x"][0].item() == 1.0
        r.release(slot)
        slot = r.pin(peek=True)
        assert slot is not None and slot.seq == a[1] + 1  # without done: the newest, queued or not
        r.release(slot)
    finally:
        ring.close()


def test_wait_done_waits_for_queued_work_and_times_each_result_by_when_it_was_done():
    ring = latest_buffer("out", SPECS, ["results"])
    try:
        r = ring.reader("results")
        w = ring.writer()
        s = w.acquire(timeout=0)
        w.publish(s, 0, 0.0, time.monotonic())
        slot = r.pin()
        assert slot is not None
        r.release(slot)

        ev = handed_off(ring)
        events = ev.events
        i, seq = publish_queued(ring, ev, 1.0)
        slot = r.pin()
        before = time.monotonic()
        t = ev.wait_done(slot)
        assert events[i].syncs == 1 and events[i].done and t >= before  # waited, then timed by the wait
        r.release(slot)

        i, seq = publish_queued(ring, ev, 2.0)
        t_done = finish(ring, ev, i, seq)
        time.sleep(0.01)
        slot = r.pin()
        assert ev.wait_done(slot) == t_done and events[i].syncs == 0  # done before: the writer's time, no wait
        r.release(slot)
    finally:
        ring.close()


def test_mark_done_wakes_a_reader_waiting_for_a_done_result(monkeypatch):
    monkeypatch.setattr(ring_module, "_MAX_SLEEP", 10.0)  # no periodic re-check: only the wake-up can end the wait
    ring = latest_buffer("out", SPECS, ["results"])
    try:
        ev = handed_off(ring)
        r = ring.reader("results")
        i, seq = publish_queued(ring, ev, 1.0)
        got: list[object] = []
        t = threading.Thread(target=lambda: got.append(r.pin(timeout=8.0, accept=ev.done)))
        t.start()
        time.sleep(0.2)
        assert t.is_alive()  # the slot is published, but queued: the reader keeps waiting
        woke = time.monotonic()
        finish(ring, ev, i, seq)
        t.join(5.0)
        assert not t.is_alive() and time.monotonic() - woke < 5.0
        assert got and got[0] is not None and got[0].seq == seq  # type: ignore[attr-defined]
        r.release(got[0])  # type: ignore[arg-type]
    finally:
        ring.close()


def test_results_without_device_events_are_done_when_published():
    ring = latest_buffer("out", SPECS, ["results"])
    try:
        w = ring.writer()
        s = w.acquire(timeout=0)
        s.tensors["x"].fill_(3.0)
        w.publish(s, 3, 0.0, time.monotonic())
        slot = ring.reader("results").pin()  # no events, no filter: published is done
        assert slot is not None and torch.equal(slot.tensors["x"], torch.full((4,), 3.0))
    finally:
        ring.close()


def test_the_first_to_see_a_result_done_says_when_and_each_result_teaches_the_prediction():
    ring = latest_buffer("out", SPECS, ["results"])
    try:
        ev = handed_off(ring)
        r = ring.reader("results")
        i, seq = publish_queued(ring, ev, 1.0)
        slot = r.pin()
        t_reader = ev.wait_done(slot)  # the reader waited: its time is the result's
        ev.mark_done(ring, slot, t_reader + 0.5)  # the writer, later: ignored
        assert ev.done_at[i] == (seq, t_reader)
        assert ev.publish_to_done_s == pytest.approx(t_reader - slot.t_publish)
        r.release(slot)
        first = ev.publish_to_done_s
        i, seq = publish_queued(ring, ev, 2.0)
        slot = ring._slot_info(i, tensors=False)
        ev.mark_done(ring, slot, slot.t_publish + first + 0.08)
        assert ev.publish_to_done_s == pytest.approx(first + 0.125 * 0.08)  # a moving average
        assert ev.publish_to_done_dev_s == pytest.approx(0.25 * 0.08)  # and its spread
    finally:
        ring.close()


class DueEvent(Event):
    """A slot's event whose 'device work' ends at ``due`` (monotonic), polled or not; ``synchronize`` sleeps until
    then. Records when it was polled and when the wait in the driver began."""

    def __init__(self, due: float) -> None:
        super().__init__()
        self.done, self.due = False, due
        self.polled_at: list[float] = []

    @property
    def polls(self) -> int:
        return len(self.polled_at)

    def query(self) -> bool:
        now = time.monotonic()
        self.polled_at.append(now)
        return now >= self.due

    def synchronize(self) -> None:
        self.sync_called_at = time.monotonic()
        time.sleep(max(0.0, self.due - self.sync_called_at))
        super().synchronize()


def publish_due(ring: SlotRing, ev: SlotEvents, value: float, work_s: float) -> tuple[int, DueEvent]:
    i, _ = publish_queued(ring, ev, value)
    slot = ring._slot_info(i, tensors=False)
    ev.events[i] = event = DueEvent(slot.t_publish + work_s)
    return i, event


@pytest.fixture
def handed_off_ring():  # type: ignore[no-untyped-def]
    """A latest-buffer output ring whose slots are handed off by (stand-in) event, and its results reader."""
    ring = latest_buffer("out", SPECS, ["results"])
    try:
        yield ring, ring.reader("results"), handed_off(ring)
    finally:
        ring.close()


# The spinning waits below run on a scale of tenths of a second, and every margin they assert is 0.1 s or more: a
# loaded CI machine (or a full garbage collection in the test's thread) can stall a thread some tens of ms.


def test_a_spinning_wait_sleeps_through_the_predicted_part_of_the_work_and_polls_only_for_the_rest(
    handed_off_ring,
):
    ring, r, ev = handed_off_ring
    i, event = publish_due(ring, ev, 1.0, 0.5)
    slot = r.pin()
    ev.wait_done(slot, spin_s=0.1)  # nothing learnt yet: no polling, the whole wait in the driver
    assert event.syncs == 1 and event.polls == 1  # the one query that found it not done yet
    r.release(slot)

    ev.publish_to_done_s = 0.6
    i, event = publish_due(ring, ev, 2.0, 0.6)
    slot = r.pin()
    t = ev.wait_done(slot, spin_s=0.1)
    assert event.syncs == 0  # done while polled: never waited in the driver
    # the first query, then a sleep through 0.6 - 0.1 s, then the polls
    assert event.polled_at[1] >= slot.t_publish + 0.5
    assert t >= event.due and t - event.due < 0.1  # polled, not slept past the end
    assert ev.done_at[i] == (slot.seq, t)
    r.release(slot)

    i, event = publish_due(ring, ev, 3.0, 0.5)
    slot = r.pin()
    ev.wait_done(slot, spin_s=0)  # no spin window: straight to the (sleeping) wait in the driver
    assert event.syncs == 1 and event.polls == 1
    r.release(slot)


def test_a_spinning_wait_polls_no_longer_than_its_window_past_the_predicted_end(handed_off_ring):
    ring, r, ev = handed_off_ring
    ev.publish_to_done_s = 0.1  # predicted: 0.1 s; the work takes 1 s
    _, event = publish_due(ring, ev, 1.0, 1.0)
    slot = r.pin()
    cpu = time.thread_time()
    t = ev.wait_done(slot, spin_s=0.1)
    spent = time.thread_time() - cpu
    # polled to the window's end (0.2 s), then waited in the driver, long before the work was done
    assert event.syncs == 1 and event.sync_called_at >= slot.t_publish + 0.1 + 0.1
    assert event.sync_called_at < event.due - 0.5
    assert t >= event.due
    assert spent < 0.5  # at most the two windows' polling, not the whole 1 s wait
    r.release(slot)


@pytest.mark.parametrize(
    "spread, work_s, polled",
    [(0.0, 1.0, False), (0.1, 0.8, True), (1.0, 1.5, False)],
    ids=["no-spread", "spread-widens-the-window", "window-capped"],
)
def test_a_spinning_wait_widens_its_window_by_the_spread_of_recent_results_up_to_a_cap(
    handed_off_ring, spread, work_s, polled
):
    ring, r, ev = handed_off_ring
    # predicted 0.5 s; window 0.2 s plus twice the spread, at most 0.4 s: polled until 0.7, 0.9 or 1.1 s
    ev.publish_to_done_s, ev.publish_to_done_dev_s = 0.5, spread
    _, event = publish_due(ring, ev, 1.0, work_s)
    slot = r.pin()
    t = ev.wait_done(slot, spin_s=0.2)
    assert t >= event.due
    assert event.syncs == (0 if polled else 1)  # the widened case's 0.8 s: past the no-spread window, inside its own
    if not polled:
        window = 0.2 + min(2 * spread, 0.4)
        assert event.sync_called_at >= slot.t_publish + 0.5 + window
        assert event.sync_called_at < slot.t_publish + 0.5 + window + 0.3
    r.release(slot)


def test_a_polling_wait_offers_the_interpreter_lock_to_other_threads(handed_off_ring):
    """A head thread woken while the caller polls must not wait for the poll to end: with a 50 ms switch interval,
    a poll that kept the lock would hold each wake-up about that long."""
    ring, r, ev = handed_off_ring
    delays: list[float] = []
    stop = threading.Event()

    def wake_up_often() -> None:
        while not stop.is_set():
            t = time.monotonic()
            time.sleep(0.001)
            delays.append(time.monotonic() - t - 0.001)

    interval = sys.getswitchinterval()
    try:
        # Generous times so that a stall of a loaded CI machine before the wait still leaves a long poll.
        ev.publish_to_done_s = 0.8
        _, event = publish_due(ring, ev, 1.0, 1.0)
        slot = r.pin()
        sys.setswitchinterval(0.05)
        other = threading.Thread(target=wake_up_often)
        other.start()
        ev.wait_done(slot, spin_s=0.8)  # polls from publish to 1 s
        stop.set()
        other.join()
        assert event.syncs == 0 and event.polls > 100
        assert len(delays) > 20 and statistics.median(delays) < 0.01
        r.release(slot)
    finally:
        sys.setswitchinterval(interval)
        stop.set()


class SlowEvent(Event):
    """A result's event whose 'device work' takes ``work_s`` from when the wait for it starts."""

    def __init__(self, work_s: float) -> None:
        super().__init__()
        self.done, self.work_s = False, work_s

    def synchronize(self) -> None:
        self.sync_started = time.monotonic()
        time.sleep(self.work_s)
        super().synchronize()


def queued_results(engine, head: str, work_s: float, predicted_s: float) -> list[SlowEvent]:  # type: ignore[no-untyped-def]
    """Make ``head``'s results look published with their device work still queued (stand-in events, as a head
    hands off on CUDA), its recent results predicting ``predicted_s`` from publish to done."""
    n = engine._res.rings[f"out.{head}"].n_slots
    ev = SlotEvents(n, blocking=True, make_event=lambda blocking: SlowEvent(work_s))
    ev.publish_to_done_s = predicted_s
    engine._handoffs.results[head] = ev
    return ev.events


def test_wait_waits_in_the_driver_for_a_result_predicted_to_be_done_in_time():
    with Engine(tiny("thread")) as e:
        fid = e.submit(frame(0))
        e.wait(fid, timeout=30)  # every head has published it
        events = queued_results(e, "depth", work_s=0.3, predicted_s=0.01)
        t0 = time.monotonic()
        res = e.wait(fid, timeout=5)
        took = time.monotonic() - t0
        assert set(res) == {"depth", "seg", "det"} and sum(ev.syncs for ev in events) == 1
        assert took >= 0.3 and res["depth"].t_publish >= t0 + 0.3  # the result is timed by its wait


def test_wait_leaves_a_result_not_predicted_to_be_done_in_time_and_keeps_its_timeout():
    with Engine(tiny("thread")) as e:
        fid = e.submit(frame(0))
        e.wait(fid, timeout=30)
        events = queued_results(e, "depth", work_s=3.0, predicted_s=3.0)
        t0 = time.monotonic()
        with pytest.raises(TimeoutError, match=r"no output from \['depth'\]"):
            e.wait(fid, timeout=0.3)
        assert time.monotonic() - t0 < 2.0 and sum(ev.syncs for ev in events) == 0  # never waited in the driver
        assert set(e.wait(fid, heads=["seg", "det"], timeout=0.3)) == {
            "seg",
            "det",
        }  # the done ones as before


def test_wait_borrows_every_result_before_it_waits_for_any_device_work(monkeypatch):
    """What can be done while the device finishes is done by then: borrowing a result's arrays reads none of its
    content, so every pinned result is borrowed before the first wait for device work begins."""
    with Engine(tiny("thread")) as e:
        fid = e.submit(frame(0))
        e.wait(fid, timeout=30)
        events = queued_results(e, "depth", work_s=0.2, predicted_s=0.01)  # waited for first: heads in config order
        borrowed_at: dict[str, float] = {}
        plain = e._outbox.leases.borrow

        def borrow(head, slot):  # type: ignore[no-untyped-def]
            borrowed_at[head] = time.monotonic()
            return plain(head, slot)

        monkeypatch.setattr(e._outbox.leases, "borrow", borrow)
        t0 = time.monotonic()
        res = e.wait(fid, timeout=5, copy=False)
        assert time.monotonic() - t0 >= 0.2 and all(r.borrowed for r in res.values())
        assert set(borrowed_at) == {"depth", "seg", "det"}
        waited = [ev.sync_started for ev in events if ev.syncs]
        assert len(waited) == 1 and max(borrowed_at.values()) < waited[0], {h: t - t0 for h, t in borrowed_at.items()}
