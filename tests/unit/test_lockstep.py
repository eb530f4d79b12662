"""Lockstep pacing's frames in flight (Note [Frames in flight] in pipeline/pacing.py) and its answering thread (Note
[Answering thread]), on a stand-in engine: how far submitting runs ahead of the answers, that every frame is answered
once, in order, each with its own outputs, and what errors and Ctrl-C on either side do."""

from __future__ import annotations

import _thread
import signal
import threading
import time
from types import SimpleNamespace

import pytest

from tests_paths import tiny
from vpengine.io.base import Frame
from vpengine.pipeline.pacing import Feed, FrameLoop, lockstep, pipelined


class Recorder:
    """Submits number frames 0, 1, ...; ``wait`` records which frames were submitted when each was answered.

    ``lag``: each wait lets the loop go on until it has submitted ``lag`` frames beyond the one waited for (or
    ``total`` frames, or for at most ``patience`` s), as a slow head would: the answer then shows how far the loop
    got."""

    def __init__(
        self,
        stop_after: int | None = None,
        lag: int = 0,
        total: int = 0,
        fail_at: int | None = None,
        error: BaseException | None = None,
        patience: float = 1.0,
    ) -> None:
        self.submitted: list[int] = []
        self.waited: list[tuple[int, int]] = []  # (frame id, frames submitted when it was answered)
        self.handled: list[int] = []
        self.threads: set[str] = set()  # where the waits ran
        self.stop = threading.Event()
        self.stop_after, self.lag, self.total = stop_after, lag, total
        self.fail_at, self.error, self.patience = fail_at, error, patience

    def submit(self, feed: Feed, frame: Frame, stamp: float | None) -> int:
        fid = len(self.submitted)
        self.submitted.append(fid)
        feed.submitted += 1
        if self.stop_after is not None and len(self.submitted) == self.stop_after:
            self.stop.set()  # a Ctrl-C while this frame is in flight
        return fid

    def wait(self, fid: int, timeout: float) -> dict[str, int]:
        self.threads.add(threading.current_thread().name)
        deadline = time.monotonic() + self.patience
        while len(self.submitted) < min(fid + self.lag, self.total) and time.monotonic() < deadline:
            time.sleep(0.001)
        if fid == self.fail_at:
            assert self.error is not None
            raise self.error
        self.waited.append((fid, len(self.submitted)))
        return {"head": fid}


def frames_then(n: int, error: Exception | None = None):  # type: ignore[no-untyped-def]
    for i in range(n):
        yield SimpleNamespace(timestamp=float(i))
    if error is not None:
        raise error


def make_loop(rec: Recorder, frames, in_flight: int, handle=None) -> FrameLoop:  # type: ignore[no-untyped-def]
    feed = Feed(None, SimpleNamespace(), 0.1, False, frames)  # type: ignore[arg-type]
    return FrameLoop(
        [feed],
        None,
        rec.stop,
        rec.submit,
        SimpleNamespace(wait=rec.wait),  # type: ignore[arg-type]
        handle or rec.handled.extend,
        lambda _: None,
        in_flight,
    )


def run(n: int, in_flight: int, stop_after: int | None = None, lag: int = 0, patience: float = 1.0) -> Recorder:
    rec = Recorder(stop_after, lag, n, patience=patience)
    lockstep(make_loop(rec, frames_then(n), in_flight))
    return rec


@pytest.mark.parametrize("in_flight", [1, 3])
def test_submitting_runs_ahead_of_the_answers_by_the_frames_in_flight_and_every_frame_is_answered_in_order(in_flight):
    rec = run(10, in_flight, lag=in_flight)
    assert [fid for fid, _ in rec.waited] == list(range(10)) and rec.handled == list(range(10))
    # frame k is answered once k + in_flight frames went in (or all of them, at the end), and no later
    assert [ahead for _, ahead in rec.waited] == [min(k + in_flight, 10) for k in range(10)]


def test_frames_are_answered_on_a_thread_of_their_own_while_the_loop_submits():
    # a wait that would let the loop run further than the frames in flight allow is answered with the bound instead
    rec = run(10, 2, lag=5, patience=0.05)
    assert rec.handled == list(range(10)) and rec.threads == {"vpengine-answers"}
    assert all(ahead <= k + 2 for k, ahead in rec.waited)


def test_after_ctrl_c_no_new_frame_goes_in_and_the_frames_in_flight_are_answered():
    rec = run(10, 3, stop_after=2)
    assert rec.submitted == [0, 1] and rec.handled == [0, 1]


def test_a_source_that_fails_raises_once_the_frames_before_it_are_answered():
    # --strict on a corrupt bag message: what came before is written, as with one frame in flight
    rec = Recorder()
    with pytest.raises(ValueError, match="corrupt"):
        lockstep(make_loop(rec, frames_then(2, ValueError("corrupt")), 3))
    assert rec.handled == [0, 1]


@pytest.mark.parametrize("side", ["wait", "handle"])
def test_an_error_while_answering_ends_the_run_with_that_error_and_nothing_after_its_frame_is_handled(side):
    # a dead engine (wait) or a failed sink (handle): raised in the loop, whose thread submits no more than in flight
    rec = Recorder(fail_at=4 if side == "wait" else None, error=RuntimeError("engine died"))

    def handle(results):  # type: ignore[no-untyped-def]
        results = list(results)
        if side == "handle" and results == [4]:
            raise RuntimeError("writing outputs failed")
        rec.handled.extend(results)

    with pytest.raises(RuntimeError, match="engine died" if side == "wait" else "writing outputs failed"):
        lockstep(make_loop(rec, frames_then(100), 3, handle))
    assert rec.handled == [0, 1, 2, 3] and len(rec.submitted) <= 4 + 3


def test_a_wait_that_times_out_is_logged_and_the_frames_after_it_are_answered(caplog):
    rec = Recorder(fail_at=1, error=TimeoutError("frame 1: no output from ['head']"))
    with caplog.at_level("WARNING", logger="vpengine.run"):
        lockstep(make_loop(rec, frames_then(4), 2))
    assert rec.handled == [0, 2, 3] and "frame 1: no output" in caplog.text


def test_a_second_ctrl_c_ends_the_run_at_once_though_a_head_never_answers():
    rec = Recorder()
    never = threading.Event()
    rec.wait = lambda fid, timeout: never.wait() and {"head": fid}  # type: ignore[method-assign]
    submit = rec.submit

    def submit_then_abort(feed, frame, stamp):  # type: ignore[no-untyped-def]
        fid = submit(feed, frame, stamp)
        if fid == 1:
            raise KeyboardInterrupt  # where the signal handler raises it on the loop's thread
        return fid

    rec.submit = submit_then_abort  # type: ignore[method-assign]
    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        lockstep(make_loop(rec, frames_then(10), 3))
    assert time.monotonic() - t0 < 1.0 and rec.handled == []
    never.set()  # the answering thread, abandoned, ends once its wait returns, and handles nothing
    time.sleep(0.1)
    assert rec.handled == []


@pytest.fixture
def python_sigint():
    """Python's own SIGINT handler, as in a terminal: a suite started in the background (``cmd &``) inherits SIGINT
    ignored, and then interrupt_main raises nothing."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_a_second_ctrl_c_while_the_frames_in_hand_are_answered_ends_the_run_at_once(python_sigint):
    # the first Ctrl-C (stop) after frame 1: the loop waits for the answers; the second (SIGINT) must not
    rec = Recorder(stop_after=2)
    never = threading.Event()
    rec.wait = lambda fid, timeout: never.wait() and {"head": fid}  # type: ignore[method-assign]
    threading.Timer(0.2, _thread.interrupt_main).start()
    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        lockstep(make_loop(rec, frames_then(10), 3))
    assert time.monotonic() - t0 < 1.5 and rec.submitted == [0, 1]
    never.set()
    time.sleep(0.1)
    assert rec.handled == []


def test_several_sources_are_answered_round_by_round_each_output_with_its_own_frame():
    rec = Recorder()
    feeds = [
        Feed(c, SimpleNamespace(), 0.1, False, frames_then(n))  # type: ignore[arg-type]
        for c, n in (("left", 3), ("right", 5))
    ]
    loop = make_loop(rec, iter(()), 2)
    loop.feeds = feeds
    lockstep(loop)
    # rounds of (left, right) while both have frames, then right alone; each frame's own output, in submit order
    assert rec.handled == rec.submitted == list(range(8))
    assert [f.submitted for f in feeds] == [3, 5]


def test_a_lockstep_run_has_every_model_read_every_frame_in_order():
    for cfg in (tiny("thread"), tiny("thread", "foundation_model.input_mode=latest", "heads.seg.input_mode=latest")):
        run_cfg, n = pipelined(cfg)
        assert n == 3 and {m.input_mode for m in (run_cfg.foundation_model, *run_cfg.heads)} == {"fifo"}
