"""Several cameras through the doors, without processes: how sources and topics are named (``NAME=SPEC``), how the
engine's cameras follow from them, the per-camera ROS 2 topics, rate commands for ``head@camera``, and the ROS 2
core fed by two cameras of different sizes (thread mode, tiny models; DDS itself in
tests/integration/test_camera_doors.py)."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest

from helpers.frames import frame
from tests_paths import TINY, tiny
from vpengine.cli.run import parse_sources
from vpengine.named_inputs import config_for_cameras, split_camera
from vpengine.pipeline.run import video_paths
from vpengine.ros2.control import model_at, parse_rate_command
from vpengine.ros2.core import Ros2Core, input_topics
from vpengine.ros2.messages import Header
from vpengine.ros2.outputs import plan_outputs


def test_a_name_is_a_camera_name_before_the_first_equals_sign():
    assert split_camera("front=camera:0") == ("front", "camera:0")
    assert split_camera("rear-2=/bags/run 1") == ("rear-2", "/bags/run 1")
    for plain in ("camera:0", "synthetic:64x64@30:3", "/topic=x", "2cams=a", "frames/*.jpg", "a b=c"):
        assert split_camera(plain) == (None, plain)


def test_sources_named_or_not(tmp_path):
    assert parse_sources(["synthetic"], []) == {None: ("synthetic", None)}
    # several unnamed ones would each be lost but one (a shell glob of images): refused, saying what to give
    with pytest.raises(ValueError, match=r"^3 sources without camera names \('a.jpg', 'b.jpg', 'c.jpg'\): a run reads"):
        parse_sources(["a.jpg", "b.jpg", "c.jpg"], [])
    with pytest.raises(ValueError, match="one bag topic a camera; name each camera's: --topic NAME=TOPIC"):
        parse_sources(["a.mcap"], ["/t", "/u"])
    assert parse_sources(["front=camera:0", "rear=bag.mcap"], ["rear=/rear/image"]) == {
        "front": ("camera:0", None),
        "rear": ("bag.mcap", "/rear/image"),
    }
    # one bag, a camera per topic
    assert parse_sources(["bag.mcap"], ["left=/l", "right=/r"]) == {
        "left": ("bag.mcap", "/l"),
        "right": ("bag.mcap", "/r"),
    }
    odd = tmp_path / "x=1.png"  # a file that exists is a file, whatever its name looks like
    odd.write_bytes(b"")
    assert parse_sources([str(odd)], []) == {None: (str(odd), None)}
    for sources, topics, message in [
        (["front=camera:0", "camera:1"], [], r"with several cameras, name each source's camera: --source NAME=SPEC"),
        (["front=a", "front=b"], [], r"--source: each camera once; repeated: \['front'\]"),
        (["front=a", "rear=b"], ["/t"], r"--topic '/t': with named sources, name the camera it is for"),
        (["front=a"], ["side=/t"], r"--topic side=/t: no source is named 'side'; sources: \['front'\]"),
        (["bag"], ["left=/l", "/r"], r"name the camera of every topic, NAME=TOPIC, or of none"),
    ]:
        with pytest.raises(ValueError, match=message):
            parse_sources(sources, topics)


def test_the_engines_cameras_are_the_sources_names_or_must_match_the_configs():
    cfg = config_for_cameras(TINY, ["rear", "front"], ["heads.seg.cameras=[front]"])
    assert cfg.camera_names() == ["rear", "front"]  # the order given is the priority order
    assert cfg.model_cameras("seg") == ["front"] and cfg.model_cameras("depth") == ["rear", "front"]
    assert config_for_cameras(TINY, None).camera_names() == ["camera"]  # one camera: as always
    two = tiny("thread", "cameras=[{name: a}, {name: b}]")
    assert config_for_cameras(two, ["b", "a"]).camera_names() == ["a", "b"]  # the config's order stands
    with pytest.raises(
        ValueError, match=r"the sources are named \['a', 'c'\] but the config's cameras are \['a', 'b'\]"
    ):
        config_for_cameras(two, ["a", "c"])
    with pytest.raises(ValueError, match=r"the config has cameras \['a', 'b'\]: give one of the input topics for each"):
        config_for_cameras(two, None, what="input topics")
    with pytest.raises(ValueError, match=r"repeated: \['a'\]"):
        config_for_cameras(TINY, ["a", "a"])


def test_several_cameras_write_a_video_each_beside_the_path_given(tmp_path):
    assert video_paths(tmp_path / "run.mp4", None) == {None: tmp_path / "run.mp4"}
    assert video_paths(tmp_path / "run.mp4", ["front", "rear"]) == {
        "front": tmp_path / "run_front.mp4",
        "rear": tmp_path / "run_rear.mp4",
    }


# ------------------------------------------------------------------------------------------------------ ROS 2
HEADS = {"depth": {"kind": "depth"}, "seg": {"kind": "segmentation"}}


def test_each_cameras_topics_are_under_its_own_namespace():
    topics, _ = plan_outputs(HEADS, "/vp", seg_overlay=True, cameras={"front": ["depth"], "rear-1": ["depth", "seg"]})
    assert [(t.camera, t.head, t.topic) for t in topics] == [
        ("front", "depth", "/vp/front/depth/depth"),
        ("rear-1", "depth", "/vp/rear_1/depth/depth"),
        ("rear-1", "seg", "/vp/rear_1/seg/classes"),
        ("rear-1", "seg", "/vp/rear_1/seg/overlay"),
    ]
    one, _ = plan_outputs(HEADS, "/vp")
    assert [t.topic for t in one] == ["/vp/depth/depth", "/vp/seg/classes"] and {t.camera for t in one} == {None}
    with pytest.raises(ValueError, match=r"'depth@a-b' and 'depth@a_b' map to the same ROS topic prefix"):
        plan_outputs(HEADS, "/vp", cameras={"a-b": ["depth"], "a_b": ["depth"]})


def test_input_topics_one_or_one_per_camera():
    assert input_topics(["/camera/image_raw"]) == "/camera/image_raw"
    assert input_topics(["front=/f/image", "rear=/r/image"]) == {"front": "/f/image", "rear": "/r/image"}
    with pytest.raises(ValueError, match="with several, name each one's camera: NAME=TOPIC"):
        input_topics(["/a", "/b"])
    with pytest.raises(ValueError, match=r"each camera once; repeated: \['f'\]"):
        input_topics(["f=/a", "f=/b"])


def test_rate_commands_may_name_one_camera():
    models, cameras = ["foundation", "depth"], ["front", "rear"]
    assert parse_rate_command("depth@rear", "5", models, cameras) == ("depth@rear", 5.0)
    assert model_at("depth@rear", models, cameras) == ("depth", "rear")
    assert model_at("depth", models, cameras) == ("depth", None)
    with pytest.raises(ValueError, match=r"'depth@side' names no camera of this engine; cameras: front, rear"):
        parse_rate_command("depth@side", "5", models, cameras)
    with pytest.raises(ValueError, match=r"unknown model 'dpth@rear'"):
        parse_rate_command("dpth@rear", "5", models, cameras)


def image_msg(arr: np.ndarray, sec: int, frame_id: str) -> SimpleNamespace:
    h, w = arr.shape[:2]
    return SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=7), frame_id=frame_id),
        height=h, width=w, encoding="bgr8", is_bigendian=0, step=w * 3, data=arr.tobytes(),
    )  # fmt: skip


def test_the_core_publishes_each_cameras_outputs_under_its_namespace_with_its_header_and_size():
    core = Ros2Core(tiny("thread"), namespace="/vp", cameras=["front", "rear"], overrides=["heads.seg.cameras=[rear]"])
    assert [t.topic for t in core.topics] == [
        "/vp/front/depth/depth", "/vp/front/det/detections",
        "/vp/rear/depth/depth", "/vp/rear/seg/classes", "/vp/rear/det/detections",
    ]  # fmt: skip
    core.start()
    try:
        assert core.handle_image(image_msg(frame(1, 120, 160), 10, "front_cam"), "front") is not None
        assert core.handle_image(image_msg(frame(2, 90, 200), 20, "rear_cam"), "rear") is not None
        assert core.handle_image(image_msg(frame(3), 30, "x"), None) is None  # which camera? refused, counted
        out: dict = {}
        deadline = time.monotonic() + 30
        while len(out) < 5 and time.monotonic() < deadline:
            out.update({t.topic: p for t, p in core.poll_outputs(0.2)})
        front, rear = out["/vp/front/depth/depth"], out["/vp/rear/depth/depth"]
        assert (front.header, front.width, front.height) == (Header(10, 7, "front_cam"), 160, 120)
        assert (rear.header, rear.width, rear.height) == (Header(20, 7, "rear_cam"), 200, 90)
        seg = out["/vp/rear/seg/classes"]
        assert (seg.header.frame_id, seg.width, seg.height) == ("rear_cam", 200, 90)
        assert max(d.center_x + d.size_x / 2 for d in out["/vp/rear/det/detections"].detections) <= 200
        assert core.set_rate("depth@rear", "2") == ("depth@rear", 2.0)
        assert core.engine.rate("depth", "rear") == 2.0 and core.engine.rate("depth", "front") is None
        with pytest.raises(ValueError, match=r"'seg' serves cameras \['rear'\], not 'front'"):
            core.set_rate("seg@front", "2")
        status = {s.name: s for s in core.diagnostics().status}
        front_status = dict(status["vp: camera front"].values)
        assert front_status["received"] == "1" and front_status["submitted"] == "1"
        assert front_status["depth.runs"] == "1" and "seg.runs" not in front_status
        assert dict(status["vp: camera rear"].values)["depth.target_hz"] == "2.00"
        assert core.counters["received"] == 3 and core.counters["rejected"] == 1
    finally:
        core.stop()
