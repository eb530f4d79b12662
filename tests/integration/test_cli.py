"""The command line end to end, as a user runs it (real console script, real processes)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from helpers.camera import FakeCamera
from tests_paths import MEDIA, ROOT, tiny

pytestmark = pytest.mark.timeout(300)


def vpengine(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    exe = shutil.which("vpengine", path=str(ROOT / ".venv" / "bin")) or shutil.which("vpengine")
    cmd = [exe, *args] if exe else [sys.executable, "-m", "vpengine.cli.main", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def test_run_on_the_street_video_writes_every_heads_outputs_and_a_summary(tmp_path):
    video = MEDIA / "vtest.avi"
    assert video.exists(), f"test media missing: {video}"
    out = tmp_path / "out"
    p = vpengine(
        "run",
        "-c",
        "configs/tiny.yaml",
        "-s",
        str(video),
        "-o",
        str(out),
        "--save-every",
        "200",
        "--viz",
        "--no-progress",
    )
    assert p.returncode == 0, p.stderr
    assert "795 frames" in p.stdout and "lockstep" in p.stdout
    s = json.loads((out / "summary.json").read_text())
    assert s["frames_submitted"] == 795 and s["pace"] == "lockstep"
    for name in ("foundation", "depth", "seg", "det"):
        m = s["models"][name]
        assert m["runs"] == 795 and m["skipped"] == 0 and m["errors"] == 0, (name, m)
    for head in ("depth", "seg", "det"):
        e2e = s["models"][head]["e2e_latency_ms"]
        assert 0 < e2e["p50"] <= e2e["p99"]
    depth = np.load(out / "depth" / "000200.npy")
    assert depth.shape == (576, 768) and depth.dtype == np.float32  # full resolution, never quantised
    assert sorted(p.name for p in (out / "depth").glob("*.npy")) == [
        f"{i:06d}.npy" for i in (0, 200, 400, 600)
    ]
    import cv2

    seg = cv2.imread(str(out / "seg" / "000400.png"), cv2.IMREAD_UNCHANGED)
    assert seg.shape == (576, 768) and seg.dtype == np.uint8
    lines = (out / "det" / "detections.jsonl").read_text().splitlines()
    assert [json.loads(x)["frame_id"] for x in lines] == list(range(795))  # one line per frame, in order
    first = json.loads(lines[0])
    assert len(first["boxes"]) == len(first["scores"]) == len(first["names"])
    assert (out / "depth" / "viz" / "000000.png").exists() and (out / "det" / "viz" / "000000.jpg").exists()


def test_run_with_the_synthetic_source_needs_no_files(tmp_path):
    p = vpengine(
        "run",
        "-c",
        "configs/tiny.yaml",
        "-s",
        "synthetic:320x240@30:60",
        "--no-progress",
        "--set",
        "heads.seg.rate_hz=10",
        "--mode",
        "thread",
        "-o",
        str(tmp_path),
    )
    assert p.returncode == 0, p.stderr
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["pace"] == "realtime" and s["frames_submitted"] == 60 and s["mode"] == "thread"
    seg = s["models"]["seg"]
    assert seg["target_hz"] == 10 and 15 <= seg["runs"] <= 22  # 2 s at 10 Hz, +-1 plus the drain
    fm = s["models"]["foundation"]
    assert fm["runs"] + fm["skipped"] == 60
    # a live source never waits for the writer (Note [Sink thread]); a result it could not write is counted
    depth = s["models"]["depth"]
    written = len(list((tmp_path / "depth").glob("*.npy")))
    assert written > 0 and written + depth["results_unwritten"] == depth["results_received"]


def test_a_camera_faster_than_the_loop_gives_its_newest_frames_and_every_frame_is_submitted_or_counted(
    tmp_path,
):
    """Note [Live capture]: a camera is read on its own thread; the loop takes the newest frame, never a stale one
    from the driver's queue, and the ones it never took are in the summary."""
    from vpengine.cli.run import format_summary, run_pipeline
    from vpengine.io.sources import VideoSource

    cam = FakeCamera(end_at=150, width=160, height=120)
    source = VideoSource(0, capture=cam)
    cam.stream(fps=300)  # faster than 2 CPU cores run three heads: frames pile up unless the newest is taken
    # lockstep: every frame taken runs through every head and is written, so the files show what was taken
    s = run_pipeline(tiny("thread"), source, tmp_path / "o", pace="lockstep", progress=False)
    assert s["frames_submitted"] + s["source_missed"] == 150 and s["source_missed"] > 0
    assert f"camera frames a newer one replaced: {s['source_missed']}" in format_summary(s)
    names = [int(p.stem) for p in sorted((tmp_path / "o" / "depth").glob("*.npy"))]
    assert len(names) == s["frames_submitted"] and names[-1] == 149  # gaps where frames were replaced


def test_image_folder_source(tmp_path):
    import cv2

    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(5):
        cv2.imwrite(str(frames / f"im{i}.png"), np.full((60, 80, 3), i * 40, np.uint8))
    out = tmp_path / "o"
    # a head paused from the start: lockstep waits for the others only
    p = vpengine(
        "run",
        "-c",
        "configs/tiny.yaml",
        "-s",
        str(frames),
        "-o",
        str(out),
        "--no-progress",
        "--set",
        "heads.seg.rate_hz=0",
    )
    assert p.returncode == 0, p.stderr
    assert sorted(x.name for x in (out / "depth").glob("*.npy")) == [f"im{i}.npy" for i in range(5)]
    s = json.loads((out / "summary.json").read_text())
    assert s["models"]["seg"]["runs"] == 0 and s["models"]["depth"]["results_received"] == 5
    assert "no output from" not in p.stderr  # never waited for the paused head


def test_config_errors_are_reported_without_a_traceback(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("heads:\n  - {name: d, model: tiny_depth, rate: 5}\n")
    p = vpengine("run", "-c", str(bad), "-s", "synthetic:64x64@30:3")
    assert p.returncode == 1
    assert "heads.0.rate: unknown key" in p.stderr and "Traceback" not in p.stderr
    p = vpengine("run", "-c", "configs/tiny.yaml", "-s", str(tmp_path / "missing.avi"))
    assert p.returncode == 1 and "does not exist" in p.stderr


def test_info_reports_versions_devices_and_mps():
    p = vpengine("info", "--json")
    assert p.returncode == 0, p.stderr
    info = json.loads(p.stdout)
    assert info["versions"]["vpengine"] and info["versions"]["torch"]
    assert info["devices"][0]["device"] == "cpu"
    assert "reachable" in info["mps"] and "pipe_directory" in info["mps"]
