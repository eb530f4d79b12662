"""`vpengine run` on live sources end to end: a real MJPEG stream on 127.0.0.1, and a camera that is not there."""

from __future__ import annotations

import json

import pytest

from helpers.streams import MjpegCamera
from tests_paths import TINY

pytestmark = pytest.mark.timeout(300)


def test_run_on_an_http_camera_paces_live_and_stops_after_max_frames(tmp_path, cli):
    with MjpegCamera(width=160, height=120, fps=30) as cam:  # served from a thread: the run may be in this process
        p = cli("run", "-c", str(TINY), "-s", cam.url, "--max-frames", "8", "--mode", "thread", "--no-progress",
                "-o", str(tmp_path / "out"))  # fmt: skip
    assert p.returncode == 0, p.stderr
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["pace"] == "realtime" and s["frames_submitted"] == 8
    assert s["models"]["foundation"]["runs"] > 0
    from vpengine.io.sinks import load_depth

    written = sorted((tmp_path / "out" / "depth").glob("*.png"))
    assert written and load_depth(tmp_path / "out" / "depth", written[-1].stem).shape == (120, 160)  # the stream's


def test_run_on_a_camera_that_is_not_there_is_one_line_and_no_opencv_chatter(tmp_path, capfd):
    from vpengine.cli.main import main

    assert main(["run", "-c", str(TINY), "-s", "camera:97", "--no-progress", "-o", str(tmp_path / "out")]) == 1
    out, err = capfd.readouterr()
    assert out == "" and err.startswith("vpengine run: error: no camera 97: /dev/video97 does not exist (")
    assert err.count("\n") == 1, err
