"""``vpengine run``'s lockstep pacing honours rate limits on the source's own timeline (Note [Answered frames]):
a rate-limited head runs on the frames its limit admits by their stamps, the others on every frame, and nobody
waits for a head that will not answer."""

from __future__ import annotations

import pytest

from tests_paths import MEDIA, tiny
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
