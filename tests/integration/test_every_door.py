"""The same frame through every door gives the same outputs, in the frame's own pixel grid (Note [Frame grid] in
boundary.py): the Python API, ``vpengine predict``, ``vpengine run`` over a folder, and a rosbag2 bag in and out.
The frame is the shipped 1080p sample; the tiny models run at 160x120, so every door must map the outputs back."""

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
from vpengine.io.sources import sample as sample_path

# one worker runs them all: the module's engine (the API's answer) starts once
pytestmark = [pytest.mark.timeout(600), pytest.mark.xdist_group("every_door")]


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    img = cv2.imread(str(sample_path("cheetah")), cv2.IMREAD_COLOR)
    assert img is not None and img.shape == (1080, 1920, 3)
    return img


# tiny_det's random weights find their boxes in the letterbox bands of a 16:9 frame, which clip to nothing in the
# frame (Note [Empty boxes]); this detector's boxes are fixed and one of them lies in the picture, so every door has
# a box to map
DET = "heads.det.model=helpers.models:EdgeBoxesDet"


@pytest.fixture(scope="module")
def api(image):
    with Engine(tiny("process", DET)) as e:
        return {h: r.outputs for h, r in e.predict(image).items()}


def boxes_of(record: dict) -> np.ndarray:
    return np.asarray(record["boxes"], np.float32).reshape(-1, 4)


def same(api, depth, classes, boxes) -> None:
    lo, hi = float(api["depth"]["depth"].min()), float(api["depth"]["depth"].max())
    assert depth.shape == classes.shape == (1080, 1920)
    np.testing.assert_allclose(depth, api["depth"]["depth"], atol=(hi - lo) / 30000 + 1e-6)  # 16-bit PNG steps
    assert (classes == api["seg"]["classes"]).all()
    np.testing.assert_allclose(boxes, api["det"]["boxes"], atol=0.01)  # the file's two decimals


def test_the_api_answers_in_the_frames_grid(api):
    assert api["depth"]["depth"].shape == (1080, 1920) and api["seg"]["classes"].shape == (1080, 1920)
    assert len(api["det"]["boxes"]) and (api["det"]["boxes"][:, 2] <= 1920).all()


def test_run_over_a_folder_gives_what_the_api_gives(tmp_path, image, api):
    (tmp_path / "in").mkdir()
    cv2.imwrite(str(tmp_path / "in" / "cheetah.png"), image)
    out = tmp_path / "out"
    assert cli(["run", "-c", "tiny", "-s", str(tmp_path / "in"), "-o", str(out), "--no-progress", "--set", DET]) == 0
    det = json.loads((out / "det" / "detections.jsonl").read_text().splitlines()[0])
    classes = cv2.imread(str(out / "seg" / "cheetah.png"), cv2.IMREAD_UNCHANGED)
    same(api, load_depth(out / "depth", "cheetah"), classes, boxes_of(det))


def test_predict_gives_what_the_api_gives(tmp_path, image, api):
    cv2.imwrite(str(tmp_path / "cheetah.png"), image)
    out = tmp_path / "pred"
    assert cli(["predict", str(tmp_path / "cheetah.png"), "-o", str(out), "--no-progress", "--exist-ok"]) == 0
    pictures = list(Path(out).rglob("*.jpg")) + list(Path(out).rglob("*.png"))
    assert pictures and all(cv2.imread(str(p)).shape[:2] == (1080, 1920) for p in pictures if "cheetah" in p.name)


def test_a_bag_in_and_out_gives_what_the_api_gives(tmp_path, image, api):
    from rosbags.rosbag2 import Reader, Writer

    from vpengine.ros2.rosbags_msgs import typestore

    ts = typestore("jazzy")
    T = ts.types
    src, dst = tmp_path / "in_bag", tmp_path / "out_bag"
    with Writer(src, version=9) as w:
        conn = w.add_connection("/cam/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=0), frame_id="cam")
        msg = T["sensor_msgs/msg/Image"](
            header=header, height=1080, width=1920, encoding="bgr8", is_bigendian=0, step=1920 * 3,
            data=image.reshape(-1),
        )  # fmt: skip
        w.write(conn, 5 * 10**9, ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))
    assert cli(["run", "-c", "tiny", "-s", str(src), "--topic", "/cam/image_raw", "--out-bag", str(dst),
                "--no-progress", "--set", DET]) == 0  # fmt: skip
    got = {}
    with Reader(dst) as r:
        for c, _, raw in r.messages():
            got[c.topic] = ts.deserialize_cdr(raw, c.msgtype)
    d, s, det = got["/vpengine/depth/depth"], got["/vpengine/seg/classes"], got["/vpengine/det/detections"]
    assert (d.width, d.height, s.width, s.height) == (1920, 1080, 1920, 1080)  # the camera's grid
    assert d.header.stamp.sec == 5 and d.header.frame_id == "cam"
    depth = d.data.view(np.float32).reshape(1080, 1920)
    classes = s.data.reshape(1080, 1920)
    centres = [
        (x.bbox.center.position.x, x.bbox.center.position.y, x.bbox.size_x, x.bbox.size_y) for x in det.detections
    ]
    boxes = np.asarray([[cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2] for cx, cy, w, h in centres], np.float32)
    boxes = boxes.reshape(-1, 4)
    np.testing.assert_allclose(depth, api["depth"]["depth"], rtol=1e-6)
    assert (classes == api["seg"]["classes"]).all()
    np.testing.assert_allclose(boxes, api["det"]["boxes"], atol=1e-3)


def test_the_ros2_core_publishes_what_the_api_gives_at_the_cameras_size(image, api):
    """The logic behind the DDS bridge and the rclpy node alike (their wire formats are tested on their own)."""
    import time
    from types import SimpleNamespace

    from vpengine.ros2.core import Ros2Core

    msg = SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=9, nanosec=0), frame_id="cam"),
        height=1080, width=1920, encoding="bgr8", is_bigendian=0, step=1920 * 3, data=image.tobytes(),
    )  # fmt: skip
    core = Ros2Core(tiny("process", DET))
    core.start()
    try:
        assert core.handle_image(msg) is not None
        out: list = []
        deadline = time.monotonic() + 60
        while len(out) < 3 and time.monotonic() < deadline:
            out += core.poll_outputs(0.2)
    finally:
        core.stop()
    got = {t.topic: p for t, p in out}
    d, s = got["/vpengine/depth/depth"], got["/vpengine/seg/classes"]
    assert (d.width, d.height, s.width, s.height) == (1920, 1080, 1920, 1080) and d.header.sec == 9
    np.testing.assert_allclose(d.data.view(np.float32).reshape(1080, 1920), api["depth"]["depth"], rtol=1e-6)
    assert (s.data.reshape(1080, 1920) == api["seg"]["classes"]).all()
    dets = got["/vpengine/det/detections"].detections
    boxes = np.asarray(
        [[x.center_x - x.size_x / 2, x.center_y - x.size_y / 2, x.center_x + x.size_x / 2, x.center_y + x.size_y / 2]
         for x in dets], np.float32,
    ).reshape(-1, 4)  # fmt: skip
    np.testing.assert_allclose(boxes, api["det"]["boxes"], atol=1e-3)
