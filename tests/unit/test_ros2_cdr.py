"""The wire format: the fast image codec, the cyclonedds IDL declarations and rosbags (an independent CDR
implementation with its own message definitions) must produce and read the very same bytes."""

from __future__ import annotations

import numpy as np
import pytest

from vpengine.ros2 import cdr
from vpengine.ros2 import dds_types as T
from vpengine.ros2.dds import dds_topic, qos
from vpengine.ros2.messages import Detection, DetectionsOut, Header, ImageOut
from vpengine.ros2.outputs import image_out
from vpengine.ros2.rosbags_msgs import to_rosbags, typestore


def pad4(b: bytes) -> bytes:
    return bytes(b) + b"\x00" * ((-len(b)) % 4)


def idl_image(img: ImageOut) -> T.Image_:
    h = img.header
    return T.Image_(
        T.Header_(T.Time_(h.sec, h.nanosec), h.frame_id),
        img.height,
        img.width,
        img.encoding,
        img.is_bigendian,
        img.step,
        img.data.tolist(),
    )


# Frame ids and encodings of every length modulo 4 move every later field across alignment boundaries.
CASES = [
    ("", "mono8", (3, 5)),
    ("c", "bgr8", (2, 3, 3)),
    ("ca", "rgb8", (1, 7, 3)),
    ("cam", "32FC1", (2, 2)),
    ("camera_optical_frame", "mono16", (3, 1)),
]


@pytest.mark.parametrize(("frame_id", "encoding", "shape"), CASES)
@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_image_encoding_matches_cyclonedds_idl_and_rosbags_byte_for_byte(frame_id, encoding, shape, distro):
    rng = np.random.default_rng(len(frame_id))
    dtype = {"32FC1": np.float32, "mono16": np.uint16}.get(encoding, np.uint8)
    arr = (rng.random(shape) * 200).astype(dtype)
    img = image_out(arr, encoding, Header(-5 if frame_id == "c" else 1_700_000_000, 999_999_999, frame_id))
    fast = bytes(cdr.encode_image(img))
    assert fast[:4] == b"\x00\x01\x00\x00" and len(fast) % 4 == 0
    assert fast == pad4(idl_image(img).serialize())
    ts = typestore(distro)
    assert fast == pad4(ts.serialize_cdr(to_rosbags(ts, img), "sensor_msgs/msg/Image"))


def test_decoding_gives_back_every_field_and_a_view_of_the_pixels():
    img = image_out(np.arange(24, dtype=np.uint8).reshape(2, 4, 3), "bgr8", Header(7, 8, "xyz"))
    raw = bytes(cdr.encode_image(img))
    v = cdr.decode_image(raw)
    assert (v.header, v.height, v.width, v.encoding, v.is_bigendian, v.step) == (
        img.header,
        2,
        4,
        "bgr8",
        0,
        12,
    )
    np.testing.assert_array_equal(v.data, img.data)
    assert np.shares_memory(v.data, np.frombuffer(raw, np.uint8))  # no copy


def test_big_endian_cdr_from_rosbags_decodes_to_the_same_message():
    ts = typestore("jazzy")
    img = image_out(np.arange(12, dtype=np.uint8).reshape(2, 2, 3), "rgb8", Header(123, 456, "be_frame"))
    be = ts.serialize_cdr(to_rosbags(ts, img), "sensor_msgs/msg/Image", little_endian=False)
    assert bytes(be[:2]) == b"\x00\x00"
    v = cdr.decode_image(be)
    assert (v.header, v.height, v.width, v.encoding, v.step) == (
        Header(123, 456, "be_frame"),
        2,
        2,
        "rgb8",
        6,
    )
    np.testing.assert_array_equal(v.data, img.data)


def test_compressed_images_round_trip_against_the_idl_and_rosbags():
    data = np.frombuffer(b"\xff\xd8\xff" + bytes(range(40)), np.uint8)
    h = Header(1, 2, "cam")
    fast = bytes(cdr.encode_compressed_image(h, "jpeg", data))
    idl = T.CompressedImage_(T.Header_(T.Time_(1, 2), "cam"), "jpeg", data.tolist())
    assert fast == pad4(idl.serialize())
    ts = typestore("humble")
    m = ts.deserialize_cdr(fast, "sensor_msgs/msg/CompressedImage")
    assert (m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id, m.format) == (1, 2, "cam", "jpeg")
    assert bytes(m.data) == data.tobytes()
    v = cdr.decode_compressed_image(fast)
    assert (v.header, v.format, v.data.tobytes()) == (h, "jpeg", data.tobytes())


def test_malformed_bytes_are_rejected_with_a_reason():
    good = bytes(cdr.encode_image(image_out(np.zeros((2, 2), np.uint8), "mono8", Header(1, 2, "f"))))
    with pytest.raises(cdr.CdrError, match=r"truncated at data"):
        cdr.decode_image(good[:-8])
    with pytest.raises(cdr.CdrError, match=r"encapsulation 0002 is not plain CDR"):
        cdr.decode_image(b"\x00\x02" + good[2:])
    with pytest.raises(cdr.CdrError, match=r"too short"):
        cdr.decode_image(b"\x00\x01")
    with pytest.raises(ValueError, match=r"image data holds 3 bytes but step x height = 2 x 2 = 4"):
        cdr.encode_image(ImageOut(Header(0, 0), 2, 2, "mono8", 0, 2, np.zeros(3, np.uint8)))


def test_detections_and_diagnostics_idl_agree_with_rosbags_vision_msgs_4():
    """Two independent declarations (cyclonedds IDL here, .msg text for rosbags) of vision_msgs 4.x."""
    from vpengine.ros2.bridge import detections_to_dds, diagnostics_to_dds
    from vpengine.ros2.diagnostics import DiagnosticsOut, Status

    d = DetectionsOut(
        Header(10, 20, "cam"),
        [Detection(30.0, 50.0, 40.0, 60.0, "person", 0.875), Detection(1.5, 2.5, 3.0, 1.0, "7", 0.5)],
    )
    idl = bytes(detections_to_dds(d).serialize())
    for distro in ("humble", "jazzy"):
        ts = typestore(distro)
        assert idl == bytes(ts.serialize_cdr(to_rosbags(ts, d), "vision_msgs/msg/Detection2DArray"))
        m = ts.deserialize_cdr(idl, "vision_msgs/msg/Detection2DArray")
        det = m.detections[0]
        assert det.bbox.center.position.x == 30.0 and det.bbox.size_y == 60.0
        assert det.results[0].hypothesis.class_id == "person" and det.results[0].hypothesis.score == 0.875
        assert det.results[0].pose.pose.orientation.w == 1.0  # ROS 2's identity quaternion
    diag = DiagnosticsOut(Header(3, 4), [Status(2, "vp: depth", "failed: x", "hw", [("runs", "5"), ("a", "")])])
    raw = bytes(diagnostics_to_dds(diag).serialize())
    m = typestore("jazzy").deserialize_cdr(raw, "diagnostic_msgs/msg/DiagnosticArray")
    s = m.status[0]
    assert (s.level, s.name, s.message, s.hardware_id) == (2, "vp: depth", "failed: x", "hw")
    assert [(kv.key, kv.value) for kv in s.values] == [("runs", "5"), ("a", "")]
    ts = typestore("jazzy")
    for cls, ros, sample in (
        (T.KeyValue_, "diagnostic_msgs/msg/KeyValue", T.KeyValue_("depth", "5")),
        (T.String_, "std_msgs/msg/String", T.String_('["foundation", "depth"]')),
    ):
        m = ts.deserialize_cdr(bytes(sample.serialize()), ros)
        assert cls(**{k: getattr(m, k) for k in cls.__dataclass_fields__}) == sample


def test_dds_names_follow_the_ros2_conventions():
    for ros_type, cls in T.BY_ROS_TYPE.items():
        assert cls.__idl_typename__ == T.dds_type_name(ros_type)
    assert T.Image_.__idl_typename__ == "sensor_msgs::msg::dds_::Image_"
    assert T.Detection2DArray_.__idl_typename__ == "vision_msgs::msg::dds_::Detection2DArray_"
    assert dds_topic("/camera/image_raw") == "rt/camera/image_raw"
    assert dds_topic("diagnostics") == "rt/diagnostics"
    for bad in ("/camera//x", "/9lives", "/a-b"):
        with pytest.raises(ValueError, match="is not a valid ROS 2 topic name"):
            dds_topic(bad)


@pytest.mark.xdist_group("dds")  # one DDS test at a time: no two share a domain or ports
def test_qos_profiles_are_ros2s():
    from cyclonedds.core import Policy

    default, sensor, latched = qos("default"), qos("sensor"), qos("latched")
    assert isinstance(default[Policy.Reliability], Policy.Reliability.Reliable)
    assert default[Policy.Durability] == Policy.Durability.Volatile
    assert default[Policy.History] == Policy.History.KeepLast(10)
    assert sensor[Policy.Reliability] == Policy.Reliability.BestEffort
    assert sensor[Policy.History] == Policy.History.KeepLast(5)
    assert latched[Policy.Durability] == Policy.Durability.TransientLocal
    assert latched[Policy.History] == Policy.History.KeepLast(1)
    # the outputs': reliable (every ROS 2 subscriber matches), only the newest sample kept
    latest = qos("latest")
    assert isinstance(latest[Policy.Reliability], Policy.Reliability.Reliable)
    assert latest[Policy.Durability] == Policy.Durability.Volatile
    assert latest[Policy.History] == Policy.History.KeepLast(1)
    for q in (default, sensor, latched, latest):  # XCDR1, what ROS 2 writes
        assert q[Policy.DataRepresentation] == Policy.DataRepresentation(use_cdrv0_representation=True)
    with pytest.raises(ValueError, match="accepted: default, sensor, latched, latest"):
        qos("fast")  # type: ignore[arg-type]


def _effective_receive_buffer(tmp_path, name: str, user: str, extra: str | None = None) -> str:
    """What cyclonedds makes of the bridge's configuration, read from its own config trace."""
    import os
    import time

    from vpengine.ros2.dds import DdsContext, bridge_config

    trace = tmp_path / f"{name}.txt"
    tracing = (
        f'<CycloneDDS><Domain id="any"><Tracing><Verbosity>config</Verbosity><OutputFile>{trace}</OutputFile>'
        "</Tracing></Domain></CycloneDDS>"
    )
    ctx = DdsContext(200 + os.getpid() % 30, bridge_config(extra, user=",".join(filter(None, (user, tracing)))))
    ctx.close()
    deadline = time.monotonic() + 5
    while "SocketReceiveBufferSize[@max]" not in (trace.read_text() if trace.exists() else ""):
        assert time.monotonic() < deadline
        time.sleep(0.05)
    (line,) = [ln for ln in trace.read_text().splitlines() if "SocketReceiveBufferSize[@max]" in ln]
    return line.split(": ")[-1].split(" {")[0]


@pytest.mark.xdist_group("dds")  # one DDS test at a time: no two share a domain or ports
def test_the_bridge_asks_for_a_frame_sized_receive_buffer_and_the_users_settings_win(tmp_path):
    from vpengine.ros2.dds import RECEIVE_BUFFER_BYTES, bridge_config, loopback_config

    assert RECEIVE_BUFFER_BYTES == 64 << 20
    lo_only = (
        '<CycloneDDS><Domain id="any"><General><Interfaces><NetworkInterface name="lo"/></Interfaces>'
        "</General></Domain></CycloneDDS>"
    )
    # a user's URI that pins the interface only (what a ROS user sets first) keeps its interface and gets the
    # buffer; one that sets the buffer keeps its own; an explicit extra (--loopback) comes instead of the URI
    assert _effective_receive_buffer(tmp_path, "lo_only", lo_only) == "64 MiB"
    own = lo_only.replace("</General>", '</General><Internal><SocketReceiveBufferSize max="1MB"/></Internal>')
    assert _effective_receive_buffer(tmp_path, "own", own) == "1 MiB"
    config = bridge_config(user="file:///etc/my.xml")
    assert config.index("64") < config.index("file:///etc/my.xml")
    config = bridge_config(loopback_config(), user="file:///etc/my.xml")
    assert config.index("64") < config.index("<Peer address") and "my.xml" not in config
    assert bridge_config(user="") == bridge_config(user="  ")  # an empty $CYCLONEDDS_URI adds nothing


def test_cyclonedds_private_calls_are_guarded_and_the_tested_major_is_pinned(monkeypatch):
    import re
    import sys
    from importlib.metadata import version

    from tests_paths import ROOT
    from vpengine.ros2 import dds

    pin = re.search(r'"cyclonedds>=(\d+),<(\d+)"', (ROOT / "pyproject.toml").read_text())
    assert pin and (int(pin[1]), int(pin[2])) == (dds.TESTED_MAJOR, dds.TESTED_MAJOR + 1)
    assert int(version("cyclonedds").split(".")[0]) == dds.TESTED_MAJOR
    monkeypatch.setitem(sys.modules, "cyclonedds._clayer", None)  # a cyclonedds without them
    with pytest.raises(ImportError) as e:
        dds._private_api()
    text = str(e.value)
    assert "\n" not in text and "vpengine.ros2 needs cyclonedds 11.x" in text
    assert "pip install 'cyclonedds>=11,<12'" in text
