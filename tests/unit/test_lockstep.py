"""Lockstep pacing's frames in flight (Note [Frames in flight] in pipeline/pacing.py), on a stand-in engine: how far
submitting runs ahead of the answers, and that every frame is answered once, in order, Ctrl-C included."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import pytest

from tests_paths import tiny
from vpengine.io.base import Frame
from vpengine.pipeline.pacing import Feed, FrameLoop, lockstep, pipelined


class Recorder:
    """Submits number frames 0, 1, ...; ``wait`` records which frames were submitted when each was waited for."""

    def __init__(self, stop_after: int | None = None) -> None:
        self.submitted: list[int] = []
        self.waited: list[tuple[int, int]] = []  # (frame id, frames submitted by then)
        self.handled: list[int] = []
        self.stop = threading.Event()
        self.stop_after = stop_after

    def submit(self, feed: Feed, frame: Frame, stamp: float | None) -> int:
        fid = len(self.submitted)
        self.submitted.append(fid)
        feed.submitted += 1
        if self.stop_after is not None and len(self.submitted) == self.stop_after:
            self.stop.set()  # a Ctrl-C while this frame is in flight
        return fid

    def wait(self, fid: int, timeout: float) -> dict[str, int]:
        self.waited.append((fid, len(self.submitted)))
        return {"head": fid}


def frames_then(n: int, error: Exception | None = None):  # type: ignore[no-untyped-def]
    for i in range(n):
        yield SimpleNamespace(timestamp=float(i))
    if error is not None:
        raise error


def run(n: int, in_flight: int, stop_after: int | None = None) -> Recorder:
    rec = Recorder(stop_after)
    frames = frames_then(n)
    feed = Feed(None, SimpleNamespace(), 0.1, False, frames)  # type: ignore[arg-type]
    loop = FrameLoop(
        [feed],
        None,
        rec.stop,
        rec.submit,
        SimpleNamespace(wait=rec.wait),
        rec.handled.extend,
        lambda _: None,
        in_flight,
    )  # type: ignore[arg-type]
    lockstep(loop)
    return rec


@pytest.mark.parametrize("in_flight", [1, 3])
def test_submitting_runs_ahead_of_the_answers_by_the_frames_in_flight_and_every_frame_is_answered_in_order(in_flight):
    rec = run(10, in_flight)
    assert [fid for fid, _ in rec.waited] == list(range(10)) and rec.handled == list(range(10))
    # frame k is waited for once k + in_flight frames went in (or all of them, at the end)
    assert [ahead for _, ahead in rec.waited] == [min(k + in_flight, 10) for k in range(10)]


def test_after_ctrl_c_no_new_frame_goes_in_and_the_frames_in_flight_are_answered():
    rec = run(10, 3, stop_after=2)
    assert rec.submitted == [0, 1] and rec.handled == [0, 1]


def test_a_source_that_fails_raises_once_the_frames_before_it_are_answered():
    # --strict on a corrupt bag message: what came before is written, as with one frame in flight
    rec = Recorder()
    feed = Feed(None, SimpleNamespace(), 0.1, False, frames_then(2, ValueError("corrupt")))  # type: ignore[arg-type]
    loop = FrameLoop(
        [feed], None, rec.stop, rec.submit, SimpleNamespace(wait=rec.wait), rec.handled.extend, lambda _: None, 3
    )  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="corrupt"):
        lockstep(loop)
    assert rec.handled == [0, 1]


def test_a_lockstep_run_has_every_model_read_every_frame_in_order():
    for cfg in (tiny("thread"), tiny("thread", "foundation_model.input_mode=latest", "heads.seg.input_mode=latest")):
        run_cfg, n = pipelined(cfg)
        assert n == 3 and {m.input_mode for m in (run_cfg.foundation_model, *run_cfg.heads)} == {"fifo"}
