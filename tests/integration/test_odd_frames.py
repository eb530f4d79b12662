"""Frames of any shape, down to 1x1, through every door and every writer (Note [Frame grid] in engine/boundary.py): the
Python API (predict, submit + wait), ``vpengine run --out --viz --video`` and ``vpengine predict``. Each output has
the frame's own shape, and no detection has an empty box (Note [Empty boxes])."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests_paths import tiny
from vpengine.cli.main import main as cli
from vpengine.engine import Engine
from vpengine.io.sinks import load_depth

pytestmark = pytest.mark.timeout(600)

SHAPES = [(1, 1), (1, 37), (29, 1), (2, 3)]


def image(hw: tuple[int, int]) -> np.ndarray:
    return np.random.default_rng(sum(hw)).integers(0, 256, (*hw, 3), dtype=np.uint8)


def check(outputs: dict, hw: tuple[int, int]) -> None:
    assert outputs["depth"]["depth"].shape == hw and outputs["seg"]["classes"].shape == hw
    det = outputs["det"]
    boxes = det["boxes"]
    assert len(boxes) == det["count"] and ((boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])).all()


def test_the_api_answers_a_frame_of_any_shape_at_its_shape():
    with Engine(tiny("thread")) as e:
        for hw in SHAPES:
            out = e.predict(image(hw))
            check(out, hw)
            assert all(r.plot().shape == (*hw, 3) for r in out.values())
            check(e.wait(e.submit(image(hw)), timeout=60), hw)


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("odd") / "in"
    d.mkdir()
    for hw in SHAPES:
        cv2.imwrite(str(d / f"{hw[0]}x{hw[1]}.png"), image(hw))
    return d


def test_run_writes_every_output_picture_and_video_of_odd_frames_at_their_shape(folder, tmp_path):
    out, mp4 = tmp_path / "out", tmp_path / "v.mp4"
    args = ["run", "-c", "tiny", "--mode", "thread", "-s", str(folder), "-o", str(out), "--viz", "--video", str(mp4)]
    assert cli([*args, "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames_submitted"] == len(SHAPES) and not summary["interrupted"]
    lines = [json.loads(x) for x in (out / "det" / "detections.jsonl").read_text().splitlines()]
    assert len(lines) == len(SHAPES)
    for hw in SHAPES:
        name = f"{hw[0]}x{hw[1]}"
        assert load_depth(out / "depth", name).shape == hw  # a 300x1 map was written transposed
        assert cv2.imread(str(out / "seg" / f"{name}.png"), cv2.IMREAD_UNCHANGED).shape == hw
        for head in ("depth", "seg", "det"):
            assert cv2.imread(str(out / head / "viz" / f"{name}.jpg")).shape == (*hw, 3)
    for rec in lines:
        assert all(x2 > x1 and y2 > y1 for x1, y1, x2, y2 in rec["boxes"])
    cap = cv2.VideoCapture(str(mp4))
    assert cap.get(cv2.CAP_PROP_FRAME_COUNT) == len(SHAPES)
    cap.release()


def test_predict_draws_odd_frames(folder, tmp_path):
    out = tmp_path / "pred"
    assert cli(["predict", "-c", "tiny", "--mode", "thread", str(folder), "-o", str(out), "--no-progress"]) == 0
    assert sorted(p.name for p in out.glob("*.jpg")) == sorted(f"{h}x{w}.jpg" for h, w in SHAPES)
    assert (out / "summary.json").is_file()


@pytest.mark.parametrize(
    ("grid", "hw", "copy"),
    [("frame", (120, 160), True), ("native", (90, 200), True), ("frame", (120, 160), False)],
    ids=["frame-of-canvas-size", "native-grid", "borrowed"],
)
def test_a_heads_own_empty_box_is_never_returned(grid, hw, copy):
    """Note [Empty boxes]: boxes that are not mapped (a frame of the canvas's size, the native grid, a borrowed
    result) lose their empty ones too; only the real box is left, in its row, with the count lowered."""
    cfg = tiny("thread", "heads.det.model=helpers.models:EdgeBoxesDet", f"heads.det.output.grid={grid}")
    with Engine(cfg) as e:
        fid = e.submit(image(hw))
        det = e.wait(fid, heads=["det"], timeout=30, copy=copy)["det"]
        assert det.grid == grid
        assert det["count"] == 1 and len(det["boxes"]) == 1 and det["labels"].tolist() == [2], det.outputs
        if grid == "native" or hw == (120, 160):
            assert det["boxes"].tolist() == [[20.0, 10.0, 60.0, 50.0]]
