"""The transport-agnostic ROS 2 core: decoding, topics, header book, detections, rate and priority commands,
diagnostics.

No DDS and no processes here; the engine tests use the real engine in thread mode with the tiny models.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np
import pytest

from helpers.frames import frame
from helpers.waiting import Commands
from tests_paths import tiny
from vpengine import checks
from vpengine.recent_frames import RecentFrames
from vpengine.ros2.control import ControlLoop, parse_priority, parse_rate, parse_rate_command
from vpengine.ros2.core import Ros2Core
from vpengine.ros2.diagnostics import ERROR, OK, WARN, Rejections, model_status, receive_buffer_advice
from vpengine.ros2.messages import Header, InputError, compressed_to_frame, image_to_frame
from vpengine.ros2.outputs import detections_out, normalize_namespace, plan_outputs

STAMP = SimpleNamespace(sec=1_700_000_123, nanosec=987_654_321)


def image_msg(arr: np.ndarray, encoding: str, pad: int = 0, big: int = 0, frame_id: str = "cam", stamp=STAMP):
    """A duck-typed sensor_msgs/Image with ``pad`` bytes of padding after every row."""
    h, w = arr.shape[:2]
    rows = arr.reshape(h, -1)
    if pad:
        rows = np.concatenate([rows, np.full((h, pad), 0xAB, np.uint8)], axis=1)
    return SimpleNamespace(
        header=SimpleNamespace(stamp=stamp, frame_id=frame_id),
        height=h,
        width=w,
        encoding=encoding,
        is_bigendian=big,
        step=rows.shape[1],
        data=rows.tobytes(),
    )


# ------------------------------------------------------------------------------------------------ import
_IMPORT_AND_SUBMIT = """
import importlib, pkgutil, time, warnings
import cv2, cyclonedds.core, numpy, torch, vpengine.engine, vpengine.visualize  # filters of their own are not ours
before = list(warnings.filters)
import vpengine.ros2
for m in pkgutil.iter_modules(vpengine.ros2.__path__):
    if m.name != "node":  # the rclpy node needs a ROS 2 installation
        importlib.import_module("vpengine.ros2." + m.name)
added = [f for f in warnings.filters if f not in before]
assert warnings.filters == before, f"importing vpengine.ros2 changed warnings.filters: {added}"

from helpers.frames import frame
from tests_paths import tiny
from vpengine.ros2 import cdr
from vpengine.ros2.core import Ros2Core
from vpengine.ros2.messages import Header
from vpengine.ros2.outputs import image_out

warnings.simplefilter("error")  # any warning on the way in or out fails
msg = cdr.decode_image(bytes(cdr.encode_image(image_out(frame(1), "bgr8", Header(1, 2)))))
assert not msg.data.flags.writeable  # a view of the received bytes, as the bridge hands it in
core = Ros2Core(tiny("thread"), seg_overlay=True)
core.start()
try:
    assert core.handle_image(msg) is not None, core.rejected.counts
    out, deadline = [], time.monotonic() + 60
    while len(out) < len(core.topics) and time.monotonic() < deadline:
        out += core.poll_outputs(0.2)
    assert len(out) == len(core.topics), out
finally:
    core.stop()
"""


@pytest.mark.timeout(200)
def test_importing_ros2_changes_no_warning_filter_and_read_only_frames_go_through_without_warnings():
    """Importing vpengine.ros2 changes nothing global, and nothing needs it to: a frame that is a read-only view of
    received bytes goes in and its outputs come out with every warning an error. A fresh interpreter, since PyTorch
    warns about a read-only array once per process, and this one has already imported everything."""
    import os
    import subprocess
    import sys

    from tests_paths import ROOT

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT / "tests")])}
    p = subprocess.run([sys.executable, "-c", _IMPORT_AND_SUBMIT], env=env, capture_output=True, text=True, timeout=180)
    assert p.returncode == 0, p.stderr[-3000:]


# ------------------------------------------------------------------------------------------------ decoding
def test_bgr8_without_padding_is_a_zero_copy_view_of_the_message_bytes():
    img = frame(3)
    msg = image_msg(img, "bgr8")
    out = image_to_frame(msg, "bgr")
    assert out.shape == (120, 160, 3) and out.flags.c_contiguous
    np.testing.assert_array_equal(out, img)
    assert np.shares_memory(out, np.frombuffer(msg.data, np.uint8))


def test_rgb8_is_converted_to_the_engines_channel_order():
    img = frame(4)
    rgb = np.ascontiguousarray(img[..., ::-1])
    np.testing.assert_array_equal(image_to_frame(image_msg(rgb, "rgb8"), "bgr"), img)
    np.testing.assert_array_equal(image_to_frame(image_msg(rgb, "rgb8"), "rgb"), rgb)
    np.testing.assert_array_equal(image_to_frame(image_msg(img, "bgr8"), "rgb"), rgb)


def test_mono8_becomes_three_equal_channels():
    grey = frame(5)[..., 1].copy()
    out = image_to_frame(image_msg(grey, "mono8"), "bgr")
    assert out.shape == (120, 160, 3)
    for c in range(3):
        np.testing.assert_array_equal(out[..., c], grey)


@pytest.mark.parametrize("encoding", ["bgr8", "rgb8", "mono8"])
def test_row_padding_is_skipped_and_byte_order_does_not_matter_for_8_bit_pixels(encoding):
    img = frame(6) if encoding != "mono8" else frame(6)[..., 0].copy()
    plain = image_to_frame(image_msg(img, encoding), "bgr")
    for pad, big in ((5, 0), (64, 1), (0, 1)):
        padded = image_to_frame(image_msg(img, encoding, pad=pad, big=big), "bgr")
        np.testing.assert_array_equal(padded, plain)


@pytest.mark.parametrize("encoding", ["16UC1", "bgra8", "32FC1", "bayer_rggb8", ""])
def test_other_encodings_fail_naming_the_encoding_and_the_accepted_ones(encoding):
    msg = image_msg(frame(1), "bgr8")
    msg.encoding = encoding
    with pytest.raises(InputError, match=rf"encoding '{encoding}' is not supported; accepted: rgb8, bgr8, mono8"):
        image_to_frame(msg)


def test_channel_swaps_at_1080p_cost_a_fraction_of_a_numpy_swap():
    """rgb8 and mono8 at 1080p go through cv2.cvtColor: the previous numpy ``[..., ::-1]`` copy took 7-26 ms a
    frame on the bridge's input thread. Compared on this machine, now, best of 5 each, so load shifts both."""
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (1080, 1920, 3), dtype=np.uint8)
    msg = image_msg(rgb, "rgb8")
    view = np.frombuffer(msg.data, np.uint8).reshape(1080, 1920, 3)

    def best(f) -> float:
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            f()
            times.append(time.perf_counter() - t0)
        return min(times)

    numpy_swap = best(lambda: np.ascontiguousarray(view[..., ::-1]))
    np.testing.assert_array_equal(image_to_frame(msg, "bgr"), rgb[..., ::-1])
    assert best(lambda: image_to_frame(msg, "bgr")) < numpy_swap / 3
    grey = image_msg(rgb[..., 0].copy(), "mono8")
    assert best(lambda: image_to_frame(grey, "bgr")) < numpy_swap / 3


def test_inconsistent_sizes_fail_with_the_numbers():
    msg = image_msg(frame(1), "bgr8")
    msg.step = 100
    with pytest.raises(InputError, match=r"step 100 is smaller than width x channels = 160 x 3 = 480"):
        image_to_frame(msg)
    msg = image_msg(frame(1), "bgr8")
    msg.data = msg.data[:-10]
    with pytest.raises(InputError, match=r"data holds 57590 bytes; a 160x120 bgr8 image with step 480 needs 57600"):
        image_to_frame(msg)


def _compressed(img: np.ndarray, ext: str, fmt: str):
    import cv2

    ok, buf = cv2.imencode(ext, img)
    assert ok
    return SimpleNamespace(header=SimpleNamespace(stamp=STAMP, frame_id="c"), format=fmt, data=buf.tobytes())


@pytest.mark.parametrize("fmt", ["png", "bgr8; png compressed bgr8", ""])
def test_png_compressed_images_decode_exactly(fmt):
    img = frame(7)
    np.testing.assert_array_equal(compressed_to_frame(_compressed(img, ".png", fmt), "bgr"), img)
    np.testing.assert_array_equal(
        compressed_to_frame(_compressed(img, ".png", fmt), "rgb"), np.ascontiguousarray(img[..., ::-1])
    )


@pytest.mark.parametrize("fmt", ["jpeg", "rgb8; jpeg compressed bgr8", ""])
def test_jpeg_compressed_images_decode_close_to_the_original(fmt):
    img = np.zeros((120, 160, 3), np.uint8)
    img[:, :80] = (200, 30, 10)  # smooth content: jpeg keeps it within a few levels
    out = compressed_to_frame(_compressed(img, ".jpg", fmt), "bgr")
    assert out.shape == img.shape
    assert np.abs(out.astype(int) - img).mean() < 3


def test_unsupported_compressed_formats_are_named():
    msg = _compressed(frame(1), ".png", "tiff")
    with pytest.raises(InputError, match=r"format 'tiff' is not supported; accepted: jpeg, png"):
        compressed_to_frame(msg)
    msg.format = "16UC1; compressedDepth png"
    with pytest.raises(InputError, match=r"compressedDepth png' \(depth\) is not a camera image"):
        compressed_to_frame(msg)
    msg.format, msg.data = "jpeg", b"\xff\xd8\xffnot really a jpeg"
    with pytest.raises(InputError, match=r"bytes of jpeg data could not be decoded"):
        compressed_to_frame(msg)


# ------------------------------------------------------------------------------------------------- headers
def test_headers_are_kept_exactly_and_the_book_is_bounded():
    h = Header.of(SimpleNamespace(stamp=STAMP, frame_id="cam"))
    assert (h.sec, h.nanosec, h.frame_id) == (1_700_000_123, 987_654_321, "cam")
    assert Header.from_ns(h.ns, "cam") == h
    # a float cannot carry the nanoseconds: this is why outputs look headers up by frame id
    assert Header.from_seconds(h.seconds, "cam") != h
    assert abs(Header.from_seconds(h.seconds).ns - h.ns) < 1000
    book = RecentFrames[Header](frames=2, tags=3)
    for i in range(5):
        book.add(i, Header(i, i, "f"), np.full((2, 2, 3), i, np.uint8))
    assert [book.tag(i) for i in range(5)] == [
        None,
        None,
        Header(2, 2, "f"),
        Header(3, 3, "f"),
        Header(4, 4, "f"),
    ]
    assert book.frame(2) is None and int(book.frame(4)[0, 0, 0]) == 4


# -------------------------------------------------------------------------------------------------- topics
HEADS = {
    "depth": {"kind": "depth"},
    "seg-2": {"kind": "segmentation", "labels": ["a", "b"]},
    "det": {"kind": "detection", "labels": ["person", "car"]},
    "feat": {"outputs": {"emb": "float32[16]"}},
}


def test_each_head_gets_topics_by_its_kind_under_the_namespace():
    topics, unmapped = plan_outputs(HEADS, "vpengine/", depth_color=False, seg_overlay=False)
    assert [(t.head, t.role, t.topic, t.msgtype) for t in topics] == [
        ("depth", "depth", "/vpengine/depth/depth", "sensor_msgs/msg/Image"),
        ("seg-2", "classes", "/vpengine/seg_2/classes", "sensor_msgs/msg/Image"),
        ("det", "detections", "/vpengine/det/detections", "vision_msgs/msg/Detection2DArray"),
    ]
    assert unmapped == ["feat"]
    topics, _ = plan_outputs(HEADS, "/robot/vp", depth_color=True, seg_overlay=True)
    assert [t.topic for t in topics] == [
        "/robot/vp/depth/depth",
        "/robot/vp/depth/depth_color",
        "/robot/vp/seg_2/classes",
        "/robot/vp/seg_2/overlay",
        "/robot/vp/det/detections",
    ]
    with pytest.raises(ValueError, match=r"heads 'a-b' and 'a_b' map to the same ROS topic prefix '/v/a_b'"):
        plan_outputs({"a-b": {"kind": "depth"}, "a_b": {"kind": "depth"}}, "/v")
    with pytest.raises(ValueError, match=r"'my-ns' is not a valid ROS name"):
        normalize_namespace("/my-ns")


def test_detections_become_centre_size_boxes_with_label_names():
    out = {
        "boxes": np.array([[10, 20, 50, 80], [0, 0, 4, 2], [1, 1, 2, 2]], np.float32),
        "scores": np.array([0.9, 0.6, 0.1], np.float32),
        "labels": np.array([1, 7, 0], np.int32),
        "count": 2,
    }
    d = detections_out(out, ["person", "car"], Header(5, 6, "cam"))
    assert d.header == Header(5, 6, "cam") and len(d.detections) == 2  # count trims the padding
    a, b = d.detections
    assert (a.center_x, a.center_y, a.size_x, a.size_y, a.class_id) == (30, 50, 40, 60, "car")
    assert a.score == pytest.approx(0.9)
    assert b.class_id == "7"  # no name for class 7: the id as text


# ------------------------------------------------------------------------------------------------- control
def test_rate_commands_parse_hz_pause_and_unlimited_and_name_bad_values():
    assert parse_rate("5") == 5.0 and parse_rate(" 2.5 ") == 2.5 and parse_rate("0") == 0.0
    for word in ("max", "MAX", "none", "unlimited", "inf", "-1"):
        assert parse_rate(word) is None
    for bad in ("fast", "-3", "nan", "1e999", "1e9"):  # 1e9: past the cap, said with the range
        with pytest.raises(
            ValueError,
            match=rf"rate '{bad}' is not a rate; accepted: a number of Hz from 0 to 10000 \(0 pauses\) or one of max, "
            r"none, null,",
        ):
            parse_rate(bad)
    assert parse_rate_command("depth", "5", ["foundation", "depth"]) == ("depth", 5.0)
    with pytest.raises(ValueError, match=r"unknown model 'dpth'; models: foundation, depth"):
        parse_rate_command("dpth", "5", ["foundation", "depth"])


def test_numeric_rates_stay_numbers_and_negative_or_infinite_ones_mean_no_limit():
    models = ["foundation", "depth"]
    assert parse_rate_command("depth", 2.5, models) == ("depth", 2.5)
    assert parse_rate_command("depth", 0, models) == ("depth", 0.0)
    for unlimited in (None, -1.0, -3, float("inf")):
        assert parse_rate_command("depth", unlimited, models) == ("depth", None)
    with pytest.raises(ValueError, match="rate nan is NaN; accepted: Hz >= 0"):
        parse_rate_command("depth", float("nan"), models)


def test_priority_commands_take_integers_in_range_and_name_bad_values():
    assert parse_priority("10") == 10 and parse_priority(" -5 ") == -5 and parse_priority(7) == 7
    assert parse_priority(str(checks.MAX_PRIORITY)) == checks.MAX_PRIORITY
    assert parse_priority(str(checks.MIN_PRIORITY)) == checks.MIN_PRIORITY
    accepted = f"from {checks.MIN_PRIORITY} to {checks.MAX_PRIORITY}"
    for bad in ("1.5", "ten", "", str(checks.MAX_PRIORITY + 1), str(checks.MIN_PRIORITY - 1), 2.0, True):
        with pytest.raises(ValueError, match=f"{accepted}.*got {bad!r}"):
            parse_priority(bad)
    assert checks.priority_target("depth") == ("depth", None)
    assert checks.priority_target(" depth@front ") == ("depth", "front")
    assert checks.priority_target("@front") == (None, "front")


def _stats(state="running", target=None, **kw):
    m = {
        "state": state,
        "target_hz": target,
        "achieved_hz": 9.5,
        "runs": 100,
        "skipped": 3,
        "dropped": 1,
        "errors": 0,
        "restarts": 0,
        "latency_ms": {"p50": 4.25, "p99": 9.5},
        "last_error": None,
    }
    m.update(kw)
    return m


def test_model_health_levels_and_values():
    s = model_status("depth", _stats(target=10.0), "vp", "hw")
    assert (s.level, s.name, s.hardware_id) == (OK, "vp: depth", "hw")
    v = dict(s.values)
    assert v["target_hz"] == "10.00" and v["achieved_hz"] == "9.50" and v["runs"] == "100"
    assert v["skipped"] == "3" and v["drops"] == "1" and v["errors"] == "0" and v["restarts"] == "0"
    assert v["latency_p50_ms"] == "4.25" and v["latency_p99_ms"] == "9.50"
    assert dict(model_status("d", _stats(), "vp", "hw").values)["target_hz"] == "unlimited"
    assert model_status("d", _stats(target=0.0), "vp", "hw").level == WARN
    assert model_status("d", _stats(state="paused", target=0.0), "vp", "hw").message == "paused (rate 0)"
    assert model_status("d", _stats(state="restarting", restarts=2), "vp", "hw").level == WARN
    failed = model_status("d", _stats(state="failed", last_error="boom"), "vp", "hw")
    assert failed.level == ERROR and "boom" in failed.message
    hung = model_status("d", _stats(state="hung", last_error="d: hung for 61 s"), "vp", "hw")
    assert hung.level == ERROR and hung.message == "hung: d: hung for 61 s"


def test_a_model_giving_way_shows_its_priority_cap_and_skips():
    skips = {"rate": 1, "priority": 4, "overload": 0}
    m = _stats(target=10.0, priority=-3, camera_priority=2, cap_hz=2.5, deadline_misses=6, skipped_by=skips)
    s = model_status("seg", m, "vp", "hw")
    v = dict(s.values)
    assert v["priority"] == "-3" and v["camera_priority"] == "2" and v["cap_hz"] == "2.50"
    assert v["deadline_misses"] == "6" and [v[f"skipped_by.{r}"] for r in skips] == ["1", "4", "0"]
    assert s.level == OK and "capped at 2.5 Hz" in s.message
    free = model_status("seg", _stats(target=10.0, priority=5, cap_hz=None), "vp", "hw")
    assert dict(free.values)["priority"] == "5" and "cap_hz" not in dict(free.values)
    assert "capped" not in free.message


# ---------------------------------------------------------------------------------------------- the core
def _poll_until(core: Ros2Core, done: Callable[[list], bool], timeout: float = 20.0) -> list:
    """Outputs until ``done(outputs so far)``, or ``timeout`` s."""
    out: list = []
    deadline = time.monotonic() + timeout
    while not done(out) and time.monotonic() < deadline:
        out += core.poll_outputs(0.2)
    return out


def _answered(core: Ros2Core, frames: int) -> Callable[[list], bool]:
    """Every topic has each of ``frames`` frames published or superseded (Note [Output QoS])."""
    return lambda out: all(
        sum(t is topic for t, _ in out) + core.outputs_superseded[topic.head] >= frames for topic in core.topics
    )


def test_keep_frames_keeps_the_input_pictures_for_a_viewer():
    assert not Ros2Core(tiny("thread")).book.keeps_frames  # no overlays, no viewer: headers only
    core = Ros2Core(tiny("thread"), keep_frames=True)
    core.start()
    try:
        img = frame(6)
        fid = core.handle_image(image_msg(np.ascontiguousarray(img[..., ::-1]), "rgb8"))
        np.testing.assert_array_equal(core.book.frame(fid), img)  # BGR, whatever the message's order
    finally:
        core.stop()


def test_core_outputs_carry_the_exact_input_header_on_every_topic():
    core = Ros2Core(tiny("thread"), depth_color=True, seg_overlay=True)
    core.start()
    try:
        sent = {}
        for i in range(3):
            h = Header(1_700_000_000 + i, 123_456_789 + i, f"cam{i}")
            stamp = SimpleNamespace(sec=h.sec, nanosec=h.nanosec)
            fid = core.handle_image(image_msg(frame(i), "bgr8", frame_id=h.frame_id, stamp=stamp))
            assert fid is not None
            sent[fid] = h
            time.sleep(0.3)
        out = _poll_until(core, _answered(core, 3))
    finally:
        core.stop()
    by_topic: dict[str, list] = {}
    for t, p in out:
        by_topic.setdefault(t.topic, []).append(p)
    assert sorted(by_topic) == sorted(t.topic for t in core.topics) and len(core.topics) == 5
    for topic, payloads in by_topic.items():
        assert {p.header for p in payloads} <= set(sent.values()), topic
        for p in payloads:
            if topic.endswith("/depth"):
                assert (p.encoding, p.width, p.height, p.step) == ("32FC1", 160, 120, 640)
                depth = p.data.view(np.float32).reshape(120, 160)
                assert np.isfinite(depth).all() and (depth > 0).all()
            elif topic.endswith("/classes"):
                assert (p.encoding, p.width, p.height, p.step) == ("mono8", 160, 120, 160)
            elif topic.endswith(("/depth_color", "/overlay")):
                assert (p.encoding, p.width, p.height, p.step) == ("bgr8", 160, 120, 480)
    assert core.counters["received"] == core.counters["submitted"] == 3
    assert core.counters["header_fallbacks"] == 0


def test_a_cameras_frame_goes_in_while_another_cameras_submit_is_still_filling():
    # each camera's input thread fills its own slot (Note [Frames of several cameras at once] in engine/core.py): a
    # camera's submit under way holds no other camera's frame back
    core = Ros2Core(tiny("thread"), cameras=["front", "rear"])
    core.start()
    try:
        eng = core.engine
        assert eng is not None
        submit, filling, go_on = eng.submit, threading.Event(), threading.Event()

        def slow_front(img, **kw):  # the front camera's submit, held in the middle of its copy
            if kw.get("camera") == "front":
                filling.set()
                assert go_on.wait(20)
            return submit(img, **kw)

        eng.submit = slow_front  # type: ignore[method-assign]
        front: list[int | None] = []
        t = threading.Thread(target=lambda: front.append(core.handle_image(image_msg(frame(1), "bgr8"), "front")))
        t.start()
        assert filling.wait(20)
        rear = core.handle_image(image_msg(frame(2), "bgr8"), "rear")  # not behind the front camera's
        go_on.set()
        t.join(20)
        assert rear is not None and front and front[0] is not None and front[0] < rear
        assert set(eng.wait(rear, timeout=30)) == {"depth", "seg", "det"}
        assert core.counters["submitted"] == 2
    finally:
        go_on.set()
        core.stop()


@pytest.mark.parametrize("every_frame", [False, True])
def test_outputs_that_waited_are_superseded_by_the_newest_unless_every_frame_is_taken(every_frame):
    """Note [Output QoS]: three results of each head wait (the output thread was busy); with newest-wins input only
    the newest goes out and the two older ones are counted, with input_mode: fifo all three go out in order."""
    from tests_paths import ROOT

    config = ROOT / "configs" / ("tiny_every_frame.yaml" if every_frame else "tiny.yaml")
    core = Ros2Core(config, overrides=["mode=thread", f"device={tiny().device}"])
    core.start()
    try:
        core.poll_outputs(0)
        for i in range(3):
            core.handle_image(image_msg(frame(i), "bgr8", stamp=SimpleNamespace(sec=100 + i, nanosec=0)))
            time.sleep(0.5)  # each head answers each frame before the next
        out = core.poll_outputs(1.0)
        values = dict({s.name: s for s in core.diagnostics().status}["vpengine: interface"].values)
    finally:
        core.stop()
    for head, topic in (("depth", "/vpengine/depth/depth"), ("det", "/vpengine/det/detections")):
        secs = [p.header.sec for t, p in out if t.topic == topic]
        assert secs == ([100, 101, 102] if every_frame else [102]), (head, secs)
        assert values[f"outputs_superseded.{head}"] == ("0" if every_frame else "2")


def test_frames_of_another_size_come_out_at_their_size_under_their_header():
    # the models run at 160x120; a 640x480 camera's outputs are published at 640x480 (Note [Frame grid])
    big = np.tile(frame(1)[:60, :80], (8, 8, 1))
    core = Ros2Core(tiny("thread"))
    core.start()
    try:
        assert core.handle_image(image_msg(big, "bgr8", stamp=SimpleNamespace(sec=7, nanosec=5))) is not None
        out = _poll_until(core, lambda out: len(out) >= 3)
        depth = next(p for t, p in out if t.role == "depth")
        classes = next(p for t, p in out if t.topic == "/vpengine/seg/classes")
        dets = next(p for t, p in out if t.topic == "/vpengine/det/detections")
        assert (depth.width, depth.height, classes.width, classes.height) == (640, 480, 640, 480)
        assert (depth.header.sec, depth.header.nanosec) == (7, 5)
        assert dets.detections and all(d.center_x <= 640 and d.center_y <= 480 for d in dets.detections)
        assert max(d.center_x + d.size_x / 2 for d in dets.detections) > 160  # the camera's pixels, not the models'
    finally:
        core.stop()


def test_first_message_size_mode_starts_the_engine_at_that_size():
    core = Ros2Core(tiny("thread"), input_size="first")
    core.start()
    try:
        assert core.engine is None
        assert all(s.level == WARN for s in core.diagnostics().status[:-1])  # "engine not started"
        with pytest.raises(ValueError, match="has not started yet"):
            core.set_rate("depth", "5")
        big = np.tile(frame(2)[:21, :28], (4, 4, 1))
        assert core.handle_image(image_msg(big, "bgr8")) is not None
        assert (core.engine.config.input.height, core.engine.config.input.width) == (84, 112)
        out = _poll_until(core, lambda out: len(out) >= 3)
        depth = next(p for t, p in out if t.role == "depth")
        assert (depth.width, depth.height) == (112, 84)
    finally:
        core.stop()


def test_core_rate_commands_reach_the_engine_and_bad_ones_are_counted():
    core = Ros2Core(tiny("thread"))
    core.start()
    try:
        assert core.set_rate("seg", "2.5") == ("seg", 2.5)
        assert core.engine.stats()["models"]["seg"]["target_hz"] == 2.5
        core.set_rate("seg", "max")
        assert core.engine.stats()["models"]["seg"]["target_hz"] is None
        core.set_rate("depth", 0.0)  # a number, as the services carry it
        assert core.engine.stats()["models"]["depth"]["target_hz"] == 0.0
        core.set_rate("depth", -1.0)  # the services' "unlimited"
        assert core.engine.stats()["models"]["depth"]["target_hz"] is None
        with pytest.raises(ValueError, match="unknown model 'nope'"):
            core.set_rate("nope", "5")
        with pytest.raises(ValueError, match="NaN"):
            core.set_rate("depth", float("nan"))
        assert core.counters["rate_commands"] == 4 and core.counters["rate_commands_rejected"] == 2
    finally:
        core.stop()


def test_core_priority_commands_reach_the_engine_and_bad_ones_change_nothing():
    core = Ros2Core(tiny("thread"))
    with pytest.raises(ValueError, match="not started"):
        core.set_priority("depth", "5")
    core.start()
    try:
        (camera,) = core.cameras

        def priorities() -> dict:
            models = core.engine.stats()["models"]
            return {h: (models[h]["priority"], models[h]["camera_priority"]) for h in ("depth", "seg", "det")}

        assert core.set_priority(" depth ", "7") == ("depth", 7)
        assert core.set_priority(f"seg@{camera}", -4) == (f"seg@{camera}", -4)  # a number, as parameters carry it
        assert core.set_priority(f"@{camera}", "3") == (f"@{camera}", 3)
        assert priorities() == {"depth": (7, 3), "seg": (-4, 3), "det": (0, 3)}
        before = priorities()
        for key, value, match in (
            ("depth", "high", "from -100 to 100.*got 'high'"),
            ("depth", "101", "got '101'"),
            ("depth", "2.5", "got '2.5'"),
            ("nope", "5", "no head named 'nope'"),
            ("foundation", "5", "follows its heads'"),
            ("depth@nocam", "5", "not 'nocam'"),
            ("@nocam", "5", r"a camera's priority \(no head named\) needs one of the cameras \[.*\], got 'nocam'"),
        ):
            with pytest.raises(ValueError, match=match):
                core.set_priority(key, value)
            assert priorities() == before, key
        assert core.counters["priority_commands"] == 3 and core.counters["priority_commands_rejected"] == 8
        assert core.counters["rate_commands"] == 0  # counted apart from rate commands
        interface = next(s for s in core.diagnostics().status if s.name.endswith(": interface"))
        assert ("priority_commands", "3") in interface.values
        depth = next(s for s in core.diagnostics().status if s.name.endswith(": depth"))
        assert ("priority", "7") in depth.values
    finally:
        core.stop()


def test_model_names_and_bad_input_messages_are_counted_not_fatal():
    core = Ros2Core(tiny("thread"))
    core.start()
    try:
        assert core.model_names == ["foundation", "depth", "seg", "det"]
        bad = image_msg(frame(1), "bgr8")
        bad.encoding = "16UC1"
        assert core.handle_image(bad) is None
        assert core.handle_image(image_msg(frame(1), "bgr8")) is not None
        assert core.counters["rejected"] == 1 and core.counters["submitted"] == 1
    finally:
        core.stop()


def test_the_bridge_submits_only_the_newest_queued_frame_unless_the_engine_takes_every_frame():
    from vpengine.ros2.bridge import frames_to_submit

    assert frames_to_submit(["a", "b", "c"], every_frame=False) == (["c"], 2)
    assert frames_to_submit(["a", "b", "c"], every_frame=True) == (["a", "b", "c"], 0)
    assert frames_to_submit(["a"], every_frame=False) == (["a"], 0)
    assert frames_to_submit([], every_frame=False) == ([], 0)


def test_the_bridge_benchmark_waits_until_diagnostics_account_for_every_run():
    from vpengine.bench.ros2_bridge import drained

    topics = ["/vpengine/depth/image", "/vpengine/seg/image"]
    status = {
        "depth": {"runs": "300"},
        "seg": {"runs": "293"},
        "interface": {
            "published:/vpengine/depth/image": "300",
            "published:/vpengine/seg/image": "188",
            "results_missed.seg": "45",
        },
    }
    assert not drained(status, topics)  # seg: 60 outputs still on their way out of the bridge
    status["interface"]["published:/vpengine/seg/image"] = "248"
    assert drained(status, topics)
    status["interface"]["published:/vpengine/seg/image"] = "238"
    assert not drained(status, topics)
    status["interface"]["outputs_superseded.seg"] = "10"  # a newer result went out instead
    assert drained(status, topics)
    assert not drained({}, topics)  # no diagnostics yet
    assert not drained({"depth": {"runs": "3"}, "interface": {}}, topics[:1])  # topic not yet published


# ------------------------------------------------------------------------------- rejections and the input link
def test_each_rejection_reason_is_logged_first_then_rate_limited_and_the_status_recovers(caplog):
    core = Ros2Core(tiny("thread"))
    now = [1000.0]
    core.rejected.clock = lambda: now[0]
    core.start()
    try:
        good = image_msg(frame(1), "bgr8")
        encoding, short, step = (
            image_msg(frame(1), "bgr8"),
            image_msg(frame(1), "bgr8"),
            image_msg(frame(1), "bgr8"),
        )
        encoding.encoding = "16UC1"
        short.data = short.data[:-10]
        step.step = 100
        with caplog.at_level("WARNING", logger="vpengine.ros2"):
            for _ in range(20):
                assert core.handle_image(encoding) is None
            assert core.handle_image(short) is None  # a different failure after the first: logged too
            assert core.handle_image(step) is None
            assert core.handle_image(SimpleNamespace(header=good.header)) is None  # not an Image at all
        lines = [r.getMessage() for r in caplog.records if "input message rejected" in r.getMessage()]
        assert len(lines) == 4, lines  # one per reason, not one per message, not only the first
        assert "(encoding)" in lines[0] and "'16UC1' is not supported" in lines[0]
        assert "(short_data)" in lines[1] and "(step)" in lines[2] and "(malformed)" in lines[3]
        iface = {s.name: s for s in core.diagnostics().status}["vpengine: interface"]
        values = dict(iface.values)
        assert values["rejected"] == "23" and values["rejected.encoding"] == "20"
        assert values["rejected.short_data"] == values["rejected.step"] == values["rejected.malformed"] == "1"
        assert iface.level == WARN and "encoding, malformed, short_data, step" in iface.message

        now[0] += 11.0  # past the log interval: one more line for the reason, counting what was not logged
        caplog.clear()
        with caplog.at_level("WARNING", logger="vpengine.ros2"):
            core.handle_image(encoding)
            core.handle_image(encoding)
        (line,) = [r.getMessage() for r in caplog.records]
        assert "(encoding; 21 in all, 19 not logged since the last line)" in line

        now[0] += 6.0  # good frames for longer than the window: OK again, the totals stay
        assert core.handle_image(good) is not None
        iface = {s.name: s for s in core.diagnostics().status}["vpengine: interface"]
        assert iface.level == OK and dict(iface.values)["rejected"] == "25"
    finally:
        core.stop()


def test_rejections_log_the_first_of_each_reason_and_count_the_rest():
    import logging

    logged: list[str] = []

    class Catch(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            logged.append(record.getMessage())

    logger = logging.getLogger("test.rejections")
    logger.addHandler(Catch())
    now = [0.0]
    r = Rejections("bad", logger, every_s=10.0, recent_s=5.0, clock=lambda: now[0])
    for t in range(30):  # one a second, alternating reasons, each reason's text the same
        now[0] = float(t)
        r.add("a" if t % 2 else "b", f"text {'a' if t % 2 else 'b'}")
    assert r.counts == {"a": 15, "b": 15} and r.total == 30
    assert logged == [
        "bad (b): text b",
        "bad (a): text a",
        "bad (b; 6 in all, 4 not logged since the last line): text b",
        "bad (a; 6 in all, 4 not logged since the last line): text a",
        "bad (b; 11 in all, 4 not logged since the last line): text b",
        "bad (a; 11 in all, 4 not logged since the last line): text a",
    ]
    assert r.recent() == ["a", "b"]
    now[0] = 33.5
    assert r.recent() == ["a"]  # b's newest was at 28 s
    now[0] = 40.0
    assert r.recent() == []
    # another text of a reason within its window is said at once (a second encoding), up to DISTINCT_TEXTS of them:
    # a text that changes with every message cannot flood the log
    logged.clear()
    for t, text in enumerate(["'bgra8'", "'mono16'", "'mono16'", "'yuv'", "'rgba16'", "'x'"], start=100):
        now[0] = float(t)
        r.add("encoding", f"encoding {text} is not supported")
    assert logged == [
        "bad (encoding): encoding 'bgra8' is not supported",
        "bad (encoding): encoding 'mono16' is not supported",
        "bad (encoding): encoding 'yuv' is not supported",
    ]
    # texts that differ only in a number (which message, how many bytes) are one failure: one line a window
    logged.clear()
    for t in range(200, 240):
        now[0] = float(t)
        r.add("malformed", f"bag 'b', message {t}: not a valid sensor_msgs/msg/Image ({t % 7 + 30} bytes)")
    assert [line.split(":")[0] for line in logged] == [
        "bad (malformed)",
        "bad (malformed; 11 in all, 9 not logged since the last line)",
        "bad (malformed; 21 in all, 9 not logged since the last line)",
        "bad (malformed; 31 in all, 9 not logged since the last line)",
    ]


def test_a_matched_publisher_that_delivers_nothing_and_a_small_receive_buffer_are_warnings(monkeypatch, caplog):
    from vpengine.ros2 import core as core_module

    assert receive_buffer_advice(None, 10**7) is None  # unknown (not Linux): nothing to say
    assert receive_buffer_advice(8 << 20, 6_220_800) is None
    advice = receive_buffer_advice(212_992, 6_220_800)
    assert "limited to 212992 bytes (net.core.rmem_max), less than one 6220800-byte input frame" in advice
    assert "sudo sysctl -w net.core.rmem_max=16777216" in advice

    monkeypatch.setattr(core_module, "SILENT_AFTER_S", 0.0)
    core = Ros2Core(tiny("thread", "input.height=1080", "input.width=1920"))

    def interface():
        return {s.name: s for s in core.diagnostics().status}["vpengine: interface"]

    assert interface().level == OK  # no publisher yet: nothing is wrong with silence
    with caplog.at_level("WARNING", logger="vpengine.ros2"):
        core.note_receive_buffer(212_992)
        core.note_publishers(1)
        first, again = interface(), interface()
    assert first.level == WARN and "a publisher has been matched" in first.message
    assert "net.core.rmem_max" in first.message and dict(first.values)["receive_buffer_limit_bytes"] == "212992"
    assert again.message == first.message
    assert len([r for r in caplog.records if r.getMessage().startswith("input link:")]) == 2  # each once
    core.note_receive_buffer(64 << 20)
    assert "net.core.rmem_max" not in interface().message  # the buffer holds a 1080p frame now
    core.counters["received"] += 1  # something arrived
    assert interface().level == OK
    core.note_publishers(0)
    core.note_publishers(1)  # a new publisher: silent since it matched
    assert interface().level == WARN


# --------------------------------------------------------------------------------------------- control path
class _FakeCore:
    def __init__(self) -> None:
        self.rates: list[tuple[str, str, float]] = []
        self.priorities: list[tuple[str, str, float]] = []

    def set_rate(self, key: str, value: str):
        if key != "depth":
            raise ValueError(f"unknown model {key!r}")
        self.rates.append((key, value, time.monotonic()))
        return key, float(value)

    def set_priority(self, key: str, value: str):
        if key != "depth":
            raise ValueError(f"no head named {key!r}")
        self.priorities.append((key, value, time.monotonic()))
        return key, int(value)

    def diagnostics(self):
        return time.monotonic()


def test_the_control_loop_keeps_its_schedule_and_applies_a_command_at_once(caplog):
    import threading

    commands = Commands()
    published: list[float] = []
    refreshed: list[float] = []
    core = _FakeCore()
    period = 0.5
    loop = ControlLoop(
        core, published.append, commands.wait, period_s=period, before_diagnostics=lambda: refreshed.append(1)
    )  # type: ignore[arg-type]

    def just_after_a_beat() -> float:  # polled every 5 ms, not wait_for's 50: 'just after' is what it measures from
        n, deadline = len(published), time.monotonic() + 5
        while len(published) == n:
            assert time.monotonic() < deadline, "the control loop stopped publishing"
            time.sleep(0.005)
        return time.monotonic()

    stop = threading.Event()
    th = threading.Thread(target=loop.run, args=(stop,))
    th.start()
    try:
        time.sleep(2.1)
        n = len(published)
        assert 4 <= n <= 6, published  # at 0, 0.5, ... 2.0 s
        gaps = np.diff(published)
        assert (np.abs(gaps - period) < 0.2).all(), gaps
        # sent just after a beat, the next is a period away: a command applied within 0.15 s is applied at once, not
        # held to the next beat nor to the end of the loop's 0.2 s wait (a stall of a loaded machine is tens of ms)
        sent = just_after_a_beat()
        commands.put(("rate", "depth", "5"))
        with caplog.at_level("WARNING", logger="vpengine.ros2"):
            commands.put(("rate", "nope", "5"))
            time.sleep(0.1)  # the diagnostics the command brought are out: the next publish is the schedule's
            priority_sent = just_after_a_beat()
            commands.put(("priority", "depth", "9"))
            commands.put(("priority", "nope", "9"))
            time.sleep(period / 2)
    finally:
        stop.set()
        th.join(5)
    ((_, value, applied),) = core.rates
    assert value == "5" and applied - sent < 0.15
    after = [t for t in published if t >= applied]
    assert after and after[0] - applied < period / 2  # diagnostics right after the command, showing it
    assert any(
        "rate command {key: 'nope', value: '5'} ignored: unknown model" in r.getMessage() for r in caplog.records
    )
    ((_, value, applied),) = core.priorities  # on the same thread, at once, and shown at once
    assert value == "9" and applied - priority_sent < 0.15
    assert any(t >= applied and t - applied < period / 2 for t in published)
    assert any("priority command {key: 'nope', value: '9'} ignored: no head" in r.getMessage() for r in caplog.records)
    assert len(refreshed) == len(published)
    with pytest.raises(ValueError, match="period must be > 0 s, got 0"):
        ControlLoop(core, published.append, commands.wait, period_s=0)  # type: ignore[arg-type]


def test_a_config_for_float_frames_takes_images_from_a_topic():
    """Images decode to uint8 frames: input.dtype is for the API's callers, as in the CLI's runs."""
    core = Ros2Core(tiny("thread", "input.dtype=float32"))
    assert core.config.input.dtype == "uint8"
    core.start()
    try:
        assert core.handle_image(image_msg(frame(0), "bgr8")) is not None
        _poll_until(core, _answered(core, 1))
    finally:
        core.stop()
    assert core.counters["submitted"] == 1
