"""rosbag2 in and out: ``vpengine run --source BAG --topic T --out-bag OUT`` for sqlite3 and MCAP bags with Humble and
Jazzy message definitions, read back with rosbags and (MCAP) with the ``mcap`` reader.

Input bags are written here with rosbags; a "Humble" input bag also gets Humble's metadata layout (version 5: no
ros_distro, custom_data or type hashes), which is what Humble's rosbag2 records.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from helpers.frames import frame
from tests_paths import ROOT
from vpengine.cli.main import main as cli
from vpengine.ros2.rosbags_msgs import typestore

pytestmark = pytest.mark.timeout(300)

N = 4
COMPRESSED = "sensor_msgs/msg/CompressedImage"
FRAME_ID = "camera_optical"
STAMPS = [(1_700_000_000 + i, 100_000_007 * (i + 1) % 1_000_000_000) for i in range(N)]


def write_bag(
    path: Path,
    storage: str,
    distro: str,
    *,
    encoding: str = "bgr8",
    compressed: bool = False,
    topic: str = "/camera/image_raw",
    extra_topic: bool = True,
    corrupt: tuple[int, ...] = (),
    frames: int = N,
    sizes: list[tuple[int, int]] | None = None,
) -> None:
    """``sizes``: each frame's (height, width) (raw images only); default 120x160 for all."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = typestore(distro)
    T = ts.types
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=8 if distro == "humble" else 9, storage_plugin=plugin) as w:
        msgtype = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
        conn = w.add_connection(topic, msgtype, typestore=ts)
        other = w.add_connection("/chatter", "std_msgs/msg/String", typestore=ts) if extra_topic else None
        for i in range(frames):
            sec, nsec = STAMPS[i] if i < N else (STAMPS[-1][0] + i, 0)
            header = T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=FRAME_ID
            )
            h, wd = sizes[i] if sizes else (120, 160)
            img = frame(i, h, wd)
            if compressed:
                data = cv2.imencode(".png", img)[1].reshape(-1)
                msg = T[msgtype](header=header, format="bgr8; png compressed bgr8", data=data)
            else:
                pixels = img if encoding != "rgb8" else np.ascontiguousarray(img[..., ::-1])
                msg = T[msgtype](
                    header=header,
                    height=h,
                    width=wd,
                    encoding=encoding,
                    is_bigendian=0,
                    step=wd * 3,
                    data=pixels.reshape(-1),
                )
            raw = ts.serialize_cdr(msg, msgtype)
            if i in corrupt:  # cut short inside the header: not a message of that type at all
                raw = raw[:30]
            # log time 50 ms after the stamp, like a recorder: outputs must carry the header stamp, not this
            w.write(conn, sec * 10**9 + nsec + 50_000_000, raw)
            if other is not None:
                w.write(
                    other,
                    sec * 10**9,
                    ts.serialize_cdr(T["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String"),
                )
    if distro == "humble":  # Humble's rosbag2 writes metadata version 5
        meta_path = path / "metadata.yaml"
        meta = yaml.safe_load(meta_path.read_text())
        info = meta["rosbag2_bagfile_information"]
        info["version"] = 5
        for key in ("ros_distro", "custom_data"):
            info.pop(key, None)
        for t in info["topics_with_message_count"]:
            t["topic_metadata"].pop("type_description_hash", None)
        meta_path.write_text(yaml.safe_dump(meta, sort_keys=False))


def read_bag(path: Path, distro: str) -> dict[str, list]:
    from rosbags.rosbag2 import Reader

    ts = typestore(distro)
    out: dict[str, list] = {}
    with Reader(path) as r:
        for conn, t, raw in r.messages():
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            out.setdefault(conn.topic, []).append((conn.msgtype, t, msg))
    return out


def check_outputs(topics: dict[str, list], viz: bool = False, stamps: list | None = None) -> None:
    stamps = STAMPS if stamps is None else stamps
    want = {
        "/vpengine/input/compressed": (COMPRESSED, "jpeg", None),  # what the heads saw, once a frame
        "/vpengine/depth/depth": ("sensor_msgs/msg/Image", "32FC1", 640),
        "/vpengine/seg/classes": ("sensor_msgs/msg/Image", "mono8", 160),
        "/vpengine/det/detections": ("vision_msgs/msg/Detection2DArray", None, None),
    }
    if viz:  # pictures as JPEG on image_transport's topic (Note [Bag contents])
        want["/vpengine/depth/depth_color/compressed"] = (COMPRESSED, "jpeg", None)
        want["/vpengine/seg/overlay/compressed"] = (COMPRESSED, "jpeg", None)
    assert sorted(topics) == sorted(want)
    for topic, (msgtype, encoding, step) in want.items():
        msgs = topics[topic]
        assert len(msgs) == len(stamps), topic  # lockstep: every head answers every frame
        got = [(m.header.stamp.sec, m.header.stamp.nanosec) for _, _, m in msgs]
        assert got == stamps, topic  # the input's header stamps, exactly, in order
        for mtype, log_time, m in msgs:
            assert mtype == msgtype and m.header.frame_id == FRAME_ID
            assert log_time == m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
            if encoding == "jpeg":
                assert m.format == "bgr8; jpeg compressed bgr8"
                assert cv2.imdecode(m.data, cv2.IMREAD_COLOR).shape == (120, 160, 3)
                continue
            if encoding is None:
                for det in m.detections:
                    assert det.header.frame_id == FRAME_ID
                    assert det.results[0].hypothesis.class_id.startswith("class_")
                    assert 0 <= det.bbox.center.position.x <= 160 and det.bbox.size_x > 0
                continue
            assert (m.encoding, m.width, m.height, m.step, m.is_bigendian) == (encoding, 160, 120, step, 0)
            assert m.data.size == step * 120
            if encoding == "32FC1":
                depth = m.data.view(np.float32)
                assert np.isfinite(depth).all() and (depth > 0).all()


def run(*args: str) -> int:
    return cli(["run", "-c", str(ROOT / "configs" / "tiny.yaml"), "--no-progress", *args])


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_bag_round_trip(tmp_path, storage, distro):
    src, out = tmp_path / "in", tmp_path / "out"
    write_bag(src, storage, distro, encoding="rgb8" if distro == "humble" else "bgr8")
    rc = run(
        "-s", str(src), "--topic", "/camera/image_raw", "--out-bag", str(out),
        "--bag-storage", storage, "--bag-distro", distro, "--mode", "thread",
    )  # fmt: skip
    assert rc == 0
    meta = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["storage_identifier"] == storage and meta["version"] == (8 if distro == "humble" else 9)
    check_outputs(read_bag(out, distro))
    if storage == "mcap":
        check_mcap(out)


def test_a_bag_whose_image_size_changes_gives_outputs_at_each_frames_own_size(tmp_path, caplog):
    """Note [Frame grid]: the bag passes each frame as it is, the engine's boundary scales it; nothing is resized
    to the first frame's size."""
    src, out = tmp_path / "in", tmp_path / "out"
    sizes = [(120, 160), (120, 160), (90, 200), (90, 200)]
    write_bag(src, "sqlite3", "jazzy", sizes=sizes, extra_topic=False)
    assert run("-s", str(src), "--out-bag", str(out), "--mode", "thread") == 0
    topics = read_bag(out, "jazzy")
    for topic in ("/vpengine/depth/depth", "/vpengine/seg/classes"):
        assert [(m.height, m.width) for _, _, m in topics[topic]] == sizes, topic
    boxes = [[(d.bbox.center.position.x, d.bbox.center.position.y) for d in m.detections]
             for _, _, m in topics["/vpengine/det/detections"]]  # fmt: skip
    assert all(0 <= x <= w and 0 <= y <= h for bs, (h, w) in zip(boxes, sizes, strict=True) for x, y in bs)
    assert "resized" not in caplog.text


def check_mcap(bag: Path) -> None:
    """The ``mcap`` library reads the file: schemas, channels, log times; rosbags decodes the payloads."""
    from mcap.reader import make_reader

    ts = typestore("jazzy")
    files = list(bag.glob("*.mcap"))
    assert len(files) == 1
    seen: dict[str, int] = {}
    with files[0].open("rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            msg = ts.deserialize_cdr(message.data, schema.name)
            stamp = (msg.header.stamp.sec, msg.header.stamp.nanosec)
            assert stamp in STAMPS and message.log_time == stamp[0] * 10**9 + stamp[1]
            if schema.name == "sensor_msgs/msg/Image":
                assert (msg.width, msg.height) == (160, 120)
            elif schema.name == COMPRESSED:
                assert cv2.imdecode(msg.data, cv2.IMREAD_COLOR).shape == (120, 160, 3)
            else:
                assert schema.name == "vision_msgs/msg/Detection2DArray"
                assert "vision_msgs/Pose2D center" in schema.data.decode()  # the 4.x definition travels along
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
    assert seen == {
        "/vpengine/input/compressed": N,
        "/vpengine/depth/depth": N,
        "/vpengine/seg/classes": N,
        "/vpengine/det/detections": N,
    }


def test_a_bare_mcap_file_of_compressed_images_gives_colour_topics_in_process_mode(tmp_path, capsys):
    """The config's process mode (the engine's workers in processes of their own), on a bare .mcap file (no
    metadata.yaml). The console script runs the same main function (test_cli.py runs it in processes of its own)."""
    src, out = tmp_path / "in", tmp_path / "out"
    write_bag(src, "mcap", "jazzy", compressed=True, topic="/cam/image/compressed", extra_topic=False)
    bare = tmp_path / "cam.mcap"
    shutil.copy(next(src.glob("*.mcap")), bare)
    assert run("-s", str(bare), "--out-bag", str(out), "--viz") == 0
    printed = capsys.readouterr().out
    assert f"{N} frames" in printed and "outputs recorded to bag" in printed
    check_outputs(read_bag(out, "jazzy"), viz=True)


def test_a_bare_db3_file_is_a_bag_source_too(tmp_path):
    from vpengine.io.sources import open_source

    write_bag(tmp_path / "in", "sqlite3", "jazzy")
    with open_source(str(next((tmp_path / "in").glob("*.db3"))), topic="/camera/image_raw") as src:
        frames = list(src)
    assert len(frames) == N and (src.width, src.height) == (160, 120)
    np.testing.assert_array_equal(frames[2].image, frame(2))
    assert [f.timestamp for f in frames] == pytest.approx([s + ns * 1e-9 for s, ns in STAMPS], abs=1e-6)


def test_wrong_encoding_fails_naming_it(tmp_path, capsys):
    src = tmp_path / "in"
    write_bag(src, "mcap", "jazzy", encoding="16UC1")
    assert run("-s", str(src), "--topic", "/camera/image_raw", "--out-bag", str(tmp_path / "o")) == 1
    err = capsys.readouterr().err
    assert "encoding '16UC1' is not supported; accepted: rgb8, bgr8, mono8" in err
    assert "'/camera/image_raw'" in err and str(src) in err
    assert not (tmp_path / "o").exists()


def test_missing_topic_fails_listing_the_topics_that_exist(tmp_path, capsys):
    src = tmp_path / "in"
    write_bag(src, "sqlite3", "humble")
    assert run("-s", str(src), "--topic", "/camera/missing", "--out-bag", str(tmp_path / "o")) == 1
    err = capsys.readouterr().err
    assert "has no topic '/camera/missing'" in err
    assert "/camera/image_raw (sensor_msgs/msg/Image)" in err and "/chatter (std_msgs/msg/String)" in err
    assert run("-s", str(src), "--topic", "/chatter") == 1
    assert "carries std_msgs/msg/String; accepted: sensor_msgs/msg/Image" in capsys.readouterr().err
    assert run("-s", "synthetic:64x64@30:2", "--topic", "/camera/image_raw") == 1
    assert "applies to rosbag2 bags only" in capsys.readouterr().err


def test_an_existing_output_bag_is_never_overwritten(tmp_path, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    write_bag(src, "mcap", "jazzy")
    out.mkdir()
    assert run("-s", str(src), "--out-bag", str(out)) == 1  # the only image topic is found without --topic
    assert "exists already" in capsys.readouterr().err


def test_a_corrupt_message_is_skipped_counted_and_named_in_one_line(tmp_path, capsys, caplog):
    src, out = tmp_path / "in", tmp_path / "out"
    write_bag(src, "mcap", "jazzy", corrupt=(1,))
    with caplog.at_level("WARNING", logger="vpengine.bag"):
        assert run("-s", str(src), "--out-bag", str(out), "--mode", "thread") == 0
    printed = capsys.readouterr()
    # a bag's bad messages, as docs/ros2.md words them; no summary.json without -o, so none is pointed at
    assert "3 frames in" in printed.out and "bad messages skipped: 1 (-o DIR lists them in its summary.json)" in (
        printed.out
    )
    assert "images skipped" not in printed.out
    assert "Traceback" not in printed.err + printed.out
    lines = [r.getMessage() for r in caplog.records]
    named = f"bag {str(src)!r}, topic '/camera/image_raw', message 1: not a valid sensor_msgs/msg/Image (30 bytes)"
    assert len([ln for ln in lines if named in ln]) == 1 and all("\n" not in ln for ln in lines), lines
    assert any("1 bad messages skipped (message 1)" in ln for ln in lines)
    check_outputs(read_bag(out, "jazzy"), stamps=[STAMPS[0], *STAMPS[2:]])  # the others, in a valid bag


def test_strict_stops_at_the_first_corrupt_message_in_one_line_and_closes_the_output_bag(tmp_path, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    write_bag(src, "sqlite3", "jazzy", corrupt=(2,))
    assert run("-s", str(src), "--out-bag", str(out), "--mode", "thread", "--strict") == 1
    err = capsys.readouterr().err
    (line,) = err.strip().splitlines()  # one line, not a traceback
    assert line.startswith(f"vpengine run: error: bag {str(src)!r}, topic '/camera/image_raw', message 2: ")
    assert "not a valid sensor_msgs/msg/Image (30 bytes): SerdeError" in line
    check_outputs(read_bag(out, "jazzy"), stamps=STAMPS[:2])  # what came before, in a bag closed valid
    bad_first = tmp_path / "bad_first"
    write_bag(bad_first, "mcap", "jazzy", corrupt=(0,))
    assert run("-s", str(bad_first), "--strict") == 1  # also when the first message is the bad one
    assert ", message 0: not a valid sensor_msgs/msg/Image" in capsys.readouterr().err


def test_ctrl_c_leaves_a_valid_output_bag(tmp_path):
    """Ctrl-C in a terminal signals the whole process group (the engine's workers too): the bag is closed valid."""
    import os
    import signal
    import time

    src, out = tmp_path / "in", tmp_path / "out"
    write_bag(src, "mcap", "jazzy", frames=100)
    p = subprocess.Popen(
        [sys.executable, "-m", "vpengine.cli.main", "run", "-c", "configs/tiny.yaml", "-s", str(src),
         "--out-bag", str(out), "--pace", "realtime", "--fps", "10", "--no-progress"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 240
        while not out.exists():  # the sink is made once the engine runs
            assert p.poll() is None and time.monotonic() < deadline, p.communicate()[0]
            time.sleep(0.1)
        time.sleep(1.0)  # some 10 of the 100 frames in: every head has answered, the run is far from its end
        os.killpg(p.pid, signal.SIGINT)
        text = p.communicate(timeout=120)[0]
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130 and "interrupted" in text and "Traceback" not in text, text
    topics = read_bag(out, "jazzy")
    assert sorted(topics) == [
        "/vpengine/depth/depth",
        "/vpengine/det/detections",
        "/vpengine/input/compressed",
        "/vpengine/seg/classes",
    ]
    counts = {t: len(m) for t, m in topics.items()}
    assert min(counts.values()) >= 1 and max(counts.values()) < 100, counts  # stopped part way, closed valid
    check_mcap_readable(out)


def check_mcap_readable(bag: Path) -> None:
    from mcap.reader import make_reader

    (path,) = bag.glob("*.mcap")
    with path.open("rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None  # the footer and summary were written: closed, not cut off


def test_a_recorded_bag_holds_the_input_images_and_plays_back_as_a_source(tmp_path):
    """Note [Bag contents]: the input goes in once a frame, as JPEG with its frame's header, and ``vpengine run``
    reads the recording back from that topic with the same stamps."""
    src, out, again = tmp_path / "in", tmp_path / "out", tmp_path / "again"
    write_bag(src, "mcap", "jazzy", extra_topic=False)
    assert run("-s", str(src), "--out-bag", str(out), "--mode", "thread") == 0
    inputs = read_bag(out, "jazzy")["/vpengine/input/compressed"]
    assert [(m.header.stamp.sec, m.header.stamp.nanosec) for _, _, m in inputs] == STAMPS
    for i, (_, _, m) in enumerate(inputs):  # each its own frame (JPEG of noise is far from exact: the nearest)
        got = cv2.imdecode(m.data, cv2.IMREAD_COLOR).astype(np.int16)
        assert np.argmin([np.abs(got - frame(j)).mean() for j in range(N)]) == i
    assert (
        run("-s", str(out), "--topic", "/vpengine/input/compressed", "--out-bag", str(again), "--mode", "thread") == 0
    )
    check_outputs(read_bag(again, "jazzy"))


def test_a_bag_named_like_its_storage_file_is_refused_with_the_folder_to_give(tmp_path):
    """A rosbag2 bag is a folder: ``x.mcap`` would become ``x.mcap/x.mcap.mcap``. The Python API refuses it as the
    CLI does, before anything is written."""
    from vpengine.io.bag import BagSink

    for name, storage, written in (("x.mcap", "mcap", "x/x.mcap"), ("x.db3", "sqlite3", "x/x.db3")):
        with pytest.raises(ValueError, match="a rosbag2 bag is a folder") as e:
            BagSink(tmp_path / name, {}, storage=storage)
        assert str(e.value).endswith(f"{str(tmp_path / 'x')!r} writes {tmp_path / written}")
    assert list(tmp_path.iterdir()) == []
