"""``vpengine run``'s lockstep pacing honours rate limits on the source's own timeline (Note [Answered frames]):
a rate-limited head runs on the frames its limit admits by their stamps, the others on every frame, and nobody
waits for a head that will not answer."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from helpers.frames import frame
from tests_paths import MEDIA, tiny
from vpengine.engine.results import Result
from vpengine.io.base import Frame, Source
from vpengine.io.sinks import Sink
from vpengine.io.sources import VideoSource
from vpengine.pipeline.run import run_pipeline


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_lockstep_over_a_10fps_video_runs_a_5hz_head_on_every_second_frame(mode):
    # a slow head would throttle every frame if lockstep waited out its period (0.2 s at 5 Hz)
    cfg = tiny(mode, "heads.seg.rate_hz=5", "heads.det.rate_hz=0")
    with VideoSource(MEDIA / "vtest.avi") as src:  # 768x576 at 10 fps; the models run at 160x120
        s = run_pipeline(cfg, src, max_frames=40, progress=False)
    m = s["models"]
    assert s["frames_submitted"] == 40
    assert m["depth"]["runs"] == 40 and m["foundation"]["runs"] == 40
    assert m["seg"]["runs"] == 20 and m["seg"]["skipped"] == 20  # the frames' stamps decide, not the wall clock
    assert m["det"]["runs"] == 0  # paused: answers nothing, waits for nothing
    assert m["seg"]["results_received"] == 20 and m["depth"]["results_received"] == 40
    # waiting out seg's period on every frame takes 40 x 0.2 s = 8 s or more; a run on the frames' stamps, far less
    assert s["wall_s"] < 6.0


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_lockstep_keeps_several_frames_in_flight_and_still_runs_every_frame_through_every_head(mode):
    # Note [Frames in flight]: the models read fifo, so no head skips a frame that queued behind it, even one the
    # config has read only the newest
    with VideoSource(MEDIA / "vtest.avi") as src:
        s = run_pipeline(tiny(mode, "heads.seg.input_mode=latest"), src, max_frames=30, progress=False)
    assert s["in_flight"] == 3  # FIFO_MARGIN 4 and output.slots 4, less the round being submitted
    for name in ("foundation", "depth", "seg", "det"):
        m = s["models"][name]
        assert m["runs"] == 30 and m["skipped"] == 0 and m["dropped"] == 0, (name, m)
    for name in ("depth", "seg", "det"):
        assert s["models"][name]["results_received"] == 30


class Numbered(Source):
    """``n`` frames told apart by their content (``helpers.frames``), of another size than the models' input; the
    frame ``fail_at`` cannot be read. Records the threads that read it."""

    height, width = 90, 200

    def __init__(self, n: int, fail_at: int | None = None) -> None:
        self.n, self.fail_at = n, fail_at
        self.readers: set[str] = set()

    def __len__(self) -> int:
        return self.n

    def __iter__(self):  # type: ignore[no-untyped-def]
        for i in range(self.n):
            self.readers.add(threading.current_thread().name)
            if i == self.fail_at:
                raise ValueError(f"frame {i} is corrupt")
            yield Frame(frame(i, self.height, self.width), None, f"{i:06d}")


class Recorded(Sink):
    def __init__(self) -> None:
        self.got: list[tuple[str, int, str, np.ndarray | None]] = []

    def write(self, result: Result, image: np.ndarray | None, name: str) -> None:
        self.got.append((result.head, result.frame_id, name, image))


def run_recorded(source: Numbered, rec: Recorded) -> None:
    try:
        run_pipeline(tiny("thread"), source, sink_factories=[lambda info, served: rec], progress=False)
    finally:  # what reached the sinks, also when the run raised
        assert source.readers and all(t.startswith("vpengine-read") for t in source.readers)  # Note [Read ahead]


def test_frames_read_ahead_reach_every_head_in_order_each_output_with_its_own_frame():
    rec = Recorded()
    run_recorded(Numbered(25), rec)
    for head in ("depth", "seg", "det"):
        got = [(fid, name, image) for h, fid, name, image in rec.got if h == head]
        assert [name for _, name, _ in got] == [f"{i:06d}" for i in range(25)], head
        assert [fid for fid, _, _ in got] == sorted(fid for fid, _, _ in got)
        for _, name, image in got:
            assert image is not None and np.array_equal(image, frame(int(name), 90, 200)), (head, name)


def test_a_frame_that_cannot_be_read_ends_the_run_after_every_frame_before_it_went_through_every_head():
    rec = Recorded()
    with pytest.raises(ValueError, match="frame 7 is corrupt"):
        run_recorded(Numbered(20, fail_at=7), rec)
    for head in ("depth", "seg", "det"):
        assert [name for h, _, name, _ in rec.got if h == head] == [f"{i:06d}" for i in range(7)], head


def test_a_run_without_a_progress_bar_reads_the_engines_stats_for_its_summary_alone(monkeypatch):
    from vpengine.engine import Engine

    calls = []
    stats = Engine.stats
    monkeypatch.setattr(Engine, "stats", lambda self: calls.append(1) or stats(self))
    s = run_pipeline(tiny("thread"), Numbered(30), progress=False)
    assert s["frames_submitted"] == 30 and len(calls) == 1  # not once a frame for rates nobody sees


def test_a_realtime_run_of_two_cameras_submits_one_while_the_others_submit_is_filling(monkeypatch):
    # each camera's feed thread fills its own input slot (Note [Frames of several cameras at once] in engine/core.py)
    from vpengine.engine import Engine

    submit, front_in, rear_in = Engine.submit, threading.Event(), threading.Event()
    waited: dict[str, bool] = {}

    def meet(self, image, **kw):  # each camera's first submit: under way while the other's goes in
        camera = kw.get("camera")
        if camera == "front" and camera not in waited:
            front_in.set()
            waited[camera] = rear_in.wait(20)
        elif camera == "rear" and camera not in waited:
            waited[camera] = front_in.wait(20)
            fid = submit(self, image, **kw)
            rear_in.set()
            return fid
        return submit(self, image, **kw)

    monkeypatch.setattr(Engine, "submit", meet)
    s = run_pipeline(tiny("thread"), {"front": Numbered(10), "rear": Numbered(10)}, pace="realtime", progress=False)
    assert waited == {"front": True, "rear": True}  # one lock around both submits: one of them waits in vain
    assert s["frames_submitted"] == 20
