"""Note [Inline finish]: the hand-over of a head's run between its worker and the thread waiting for that frame,
with a stand-in worker (the engine-level behaviour is in tests/integration/test_inline_finish.py). A run is
published exactly once, by the taker or else by its worker, and never left in between."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import pytest

from vpengine.runtime.worker import InlineFinish

pytestmark = pytest.mark.timeout(30)


class Dev:
    def __init__(self, fail: bool = False) -> None:
        self.fail, self.waited = fail, []

    def mark_done(self) -> float:
        return time.monotonic()

    def wait_marked(self, t: float) -> None:
        self.waited.append(t)
        if self.fail:
            raise KeyboardInterrupt  # e.g. the waiting thread interrupted in the driver


class Core:
    """The parts of a WorkerCore the hand-over uses."""

    def __init__(self, fail: bool = False) -> None:
        self.dev = Dev(fail)
        self.published: list[tuple[object, object]] = []
        self.notified = 0
        self.control = SimpleNamespace(notify_output=self._notify)

    def _notify(self) -> None:
        self.notified += 1

    def _publish_run(self, slot: object, out: object, t_start: float) -> None:
        self.published.append((slot, out))


def slot(origin: int) -> SimpleNamespace:
    return SimpleNamespace(origin=origin)


def never() -> bool:
    return False


def test_nobody_waiting_nothing_is_handed():
    f, core = InlineFinish(), Core()
    f.want(4)
    assert f.hand(core, slot(5), "out", 0.0) is None and core.notified == 0


def test_a_taken_run_is_published_by_its_taker_and_its_worker_goes_on():
    f, core = InlineFinish(), Core()
    f.want(5)
    h = f.hand(core, slot(5), "out", 0.0)
    assert h is not None and core.notified == 1  # the waiting thread is woken to take it
    assert f.take(4) is None  # another frame's waiter does not get it
    settled: list[bool] = []
    worker = threading.Thread(target=lambda: settled.append(f.settle(h, never)))
    worker.start()
    assert f.take(5) is h and f.take(5) is None  # taken once
    f.finish(h)
    worker.join(5)
    assert settled == [True] and core.published == [(h.slot, "out")] and f.finishes == 1
    assert core.dev.waited == [h.t_marked]  # the taker waited for the device work first
    f.unwant(5)


def test_a_run_handed_to_a_thread_that_stops_waiting_goes_back_to_its_worker():
    f, core = InlineFinish(), Core()
    f.want(5)
    f.want(5)  # two threads wait for frame 5
    h = f.hand(core, slot(5), "out", 0.0)
    assert h is not None
    f.unwant(5)  # one leaves: the other may still take it
    assert h.state == "handed"
    f.unwant(5)  # nobody waits any more
    assert f.settle(h, never) is False  # the worker publishes it itself
    assert core.published == [] and f.take(5) is None
    assert f.hand(core, slot(6), "out", 0.0) is None  # and nothing is wanted now


def test_a_taker_interrupted_before_publishing_gives_the_run_back():
    f, core = InlineFinish(), Core(fail=True)
    f.want(5)
    h = f.hand(core, slot(5), "out", 0.0)
    assert f.take(5) is h
    with pytest.raises(KeyboardInterrupt):
        f.finish(h)
    assert f.settle(h, never) is False and core.published == [] and f.finishes == 0


def test_a_run_nobody_takes_comes_back_when_the_engine_stops_but_a_taken_one_is_finished():
    f, core = InlineFinish(), Core()
    f.want(5)
    h = f.hand(core, slot(5), "out", 0.0)
    assert f.settle(h, lambda: True) is False  # stopping, not taken: the worker finishes it
    h2 = f.hand(core, slot(5), "out", 0.0)
    assert f.take(5) is h2
    settled: list[bool] = []
    worker = threading.Thread(target=lambda: settled.append(f.settle(h2, lambda: True)))
    worker.start()
    time.sleep(0.1)
    assert worker.is_alive()  # taken: it waits for the taker even while stopping
    f.finish(h2)
    worker.join(5)
    assert settled == [True] and len(core.published) == 1
