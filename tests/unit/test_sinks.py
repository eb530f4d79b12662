"""Note [Sink thread]: results written on a background thread, in order, with nothing lost unless counted, and a
sink's failure raised in the caller."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from vpengine.engine import Result
from vpengine.io.sinks import Sink, SinkThread


def result(head: str, i: int) -> Result:
    return Result(head, i, float(i), 0.001, {"x": np.full(3, i)})


class Recorder(Sink):
    def __init__(self, delay_s: float = 0.0, fail_at: int | None = None, fail_close: bool = False) -> None:
        self.delay_s, self.fail_at, self.fail_close = delay_s, fail_at, fail_close
        self.written: list[tuple[str, int, str]] = []
        self.threads = {threading.current_thread().name}  # made, written and closed on
        self.closed = False
        self.gate = threading.Event()  # cleared: the writer stalls in its first write
        self.gate.set()
        self.entered = threading.Event()

    def write(self, result: Result, frame: np.ndarray | None, name: str) -> None:
        self.entered.set()
        self.gate.wait()
        if result.frame_id == self.fail_at:
            raise OSError(28, "No space left on device")
        time.sleep(self.delay_s)
        self.threads.add(threading.current_thread().name)
        self.written.append((result.head, result.frame_id, name))

    def close(self) -> None:
        self.threads.add(threading.current_thread().name)
        self.closed = True
        if self.fail_close:
            raise OSError("bag index not written")


def maker(made: list[Recorder], **kw: object):  # type: ignore[no-untyped-def]
    """A factory that makes a Recorder (in whichever thread calls it) and keeps it in ``made``."""

    def make() -> Recorder:
        made.append(Recorder(**kw))  # type: ignore[arg-type]
        return made[-1]

    return make


def test_every_result_reaches_every_sink_in_order_off_the_callers_thread():
    made: list[Recorder] = []
    w = SinkThread([maker(made, delay_s=0.002), maker(made)], max_pending=4, block=True)
    a, b = made
    for i in range(30):
        for h in ("depth", "seg"):
            w.put(result(h, i), None, f"{i:06d}")
    w.close()
    want = [(h, i, f"{i:06d}") for i in range(30) for h in ("depth", "seg")]
    assert a.written == want and b.written == want and a.closed and b.closed
    assert a.threads == b.threads == {"vpengine-sinks"} and not w.unwritten  # as an SQLite bag needs


def test_a_full_queue_waits_when_blocking_and_counts_what_it_leaves_unwritten_when_not():
    sink = Recorder()
    sink.gate.clear()  # the writer stalls on the first result
    w = SinkThread([lambda: sink], max_pending=2, block=False)
    t0 = time.monotonic()
    w.put(result("seg", 0), None, "0")
    assert sink.entered.wait(5)
    for i in range(1, 10):
        w.put(result("depth" if i % 2 else "seg", i), None, str(i))
    # one result in the writer's hands, two queued, seven left unwritten and counted per head
    assert sum(w.unwritten.values()) == 7 and set(w.unwritten) == {"depth", "seg"}
    assert time.monotonic() - t0 < 1.0  # a live loop is never held up by the writer
    sink.gate.set()
    w.close()
    assert len(sink.written) == 3 and [r[1] for r in sink.written] == [0, 1, 2]

    sink = Recorder()
    sink.gate.clear()
    w = SinkThread([lambda: sink], max_pending=2, block=True)
    w.put(result("depth", 0), None, "0")
    assert sink.entered.wait(5)
    for i in (1, 2):
        w.put(result("depth", i), None, str(i))
    t = threading.Thread(target=w.put, args=(result("depth", 3), None, "3"))
    t.start()
    t.join(0.3)
    assert t.is_alive()  # waits for room: nothing is dropped in lockstep
    sink.gate.set()
    t.join(5)
    w.close()
    assert [r[1] for r in sink.written] == [0, 1, 2, 3] and not w.unwritten


def test_a_sink_that_fails_is_raised_in_the_caller_once_and_nothing_hangs():
    sink = Recorder(fail_at=2)
    w = SinkThread([lambda: sink], max_pending=2, block=True)
    with pytest.raises(RuntimeError, match="writing outputs failed: .*No space left on device"):
        for i in range(
            1000
        ):  # a blocking put on a queue a failed writer no longer writes must not wait forever
            w.put(result("depth", i), None, str(i))
    assert [r[1] for r in sink.written] == [0, 1]
    w.close()  # already raised: not again; the sink is still closed
    assert sink.closed

    sink = Recorder(fail_at=0)
    w = SinkThread([lambda: sink], max_pending=2, block=True)
    w.put(result("depth", 0), None, "0")
    with pytest.raises(RuntimeError, match="No space left"):
        w.close()  # the caller never put again: close reports it


def test_every_sink_is_closed_even_when_one_fails_to_close():
    bad, good = Recorder(fail_close=True), Recorder()
    w = SinkThread([lambda: bad, lambda: good], max_pending=1, block=True)
    w.put(result("seg", 0), None, "0")
    with pytest.raises(RuntimeError, match="closing outputs failed: .*bag index"):
        w.close()
    assert bad.closed and good.closed and good.written == [("seg", 0, "0")]
    w.close()  # twice is fine


def test_a_sink_that_cannot_be_made_raises_its_own_error_from_the_constructor_and_the_others_are_closed():
    made: list[Recorder] = []

    def bad() -> Sink:
        raise ValueError("output bag 'x' exists already; bags are never overwritten")

    with pytest.raises(ValueError, match="exists already"):
        SinkThread([maker(made), bad], max_pending=2, block=True)
    assert made[0].closed and made[0].threads == {"vpengine-sinks"}


def test_a_queue_of_no_results_is_refused():
    with pytest.raises(ValueError, match="max_pending must be >= 1, got 0"):
        SinkThread([], max_pending=0, block=True)
