"""Several cameras through every door (issue 23): ``vpengine run`` and ``vpengine predict`` with named sources of
different sizes, a bag with two image topics in and out, and the DDS bridge with an input topic per camera. Every
camera's outputs land under its own name, at its own frames' size, with its own headers; a head limited to one
camera answers for that one alone; the summary counts per camera."""

from __future__ import annotations

import json
import time

import cv2
import pytest

from helpers.frames import frame
from tests_paths import tiny
from vpengine.cli.main import main as cli
from vpengine.io.sinks import load_depth

pytestmark = pytest.mark.timeout(300)

REAR_HW = (90, 200)  # the folder camera's frames; the synthetic front camera's are 240x320


@pytest.fixture()
def folder(tmp_path):
    d = tmp_path / "rear"
    d.mkdir()
    for i in range(4):
        cv2.imwrite(str(d / f"im{i}.png"), frame(i, *REAR_HW))
    return d


def test_run_with_two_named_sources_writes_each_cameras_outputs_at_its_size_and_counts_per_camera(
    tmp_path, folder, capsys
):
    out, video = tmp_path / "out", tmp_path / "v.mp4"
    args = ["run", "-c", "tiny", "--mode", "thread", "--no-progress", "-o", str(out), "--video", str(video),
            "-s", "front=synthetic:320x240@30:6", "-s", f"rear={folder}", "--set", "heads.seg.cameras=[rear]",
            "--pace", "lockstep"]  # fmt: skip
    assert cli(args) == 0
    printed = capsys.readouterr().out
    assert "10 frames (front 6, rear 4)" in printed and "seg@rear" in printed and "seg@front" not in printed
    # DIR/<camera>/<head>/..., every map at its camera's size; seg serves the rear camera alone
    assert sorted(p.name for p in out.iterdir()) == ["front", "rear", "summary.json"]
    assert sorted(p.name for p in (out / "front").iterdir()) == ["depth", "det"]
    assert sorted(p.name for p in (out / "rear").iterdir()) == ["depth", "det", "seg"]
    assert load_depth(out / "front" / "depth", "000005").shape == (240, 320)
    assert load_depth(out / "rear" / "depth", "im3").shape == REAR_HW
    classes = cv2.imread(str(out / "rear" / "seg" / "im0.png"), cv2.IMREAD_UNCHANGED)
    assert classes.shape == REAR_HW
    lines = [json.loads(x) for x in (out / "rear" / "det" / "detections.jsonl").read_text().splitlines()]
    assert [x["frame"] for x in lines] == ["im0", "im1", "im2", "im3"]
    assert all(b[2] <= REAR_HW[1] and b[3] <= REAR_HW[0] for x in lines for b in x["boxes"])
    s = json.loads((out / "summary.json").read_text())
    assert s["frames_submitted"] == 10 and s["models"]["foundation"]["runs"] == 10  # a source that ends stops alone
    front, rear = s["cameras"]["front"], s["cameras"]["rear"]
    assert (front["frames_submitted"], rear["frames_submitted"]) == (6, 4)
    assert set(front["models"]) == {"foundation", "depth", "det"} and rear["models"]["seg"]["runs"] == 4
    assert front["models"]["depth"]["runs"] == front["models"]["depth"]["results_received"] == 6
    assert s["models"]["seg"]["runs"] == 4 and s["models"]["depth"]["runs"] == 10
    # one annotated video per camera, beside the path given, at each camera's own picture size
    for camera, n in (("front", 6), ("rear", 4)):
        cap = cv2.VideoCapture(str(tmp_path / f"v_{camera}.mp4"))
        assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == n
        cap.release()
    assert not video.exists()


def test_realtime_feeds_each_camera_at_its_own_rate_until_its_own_end(tmp_path):
    from vpengine.io.sources import SyntheticSource
    from vpengine.pipeline.run import run_pipeline

    sources = {"fast": SyntheticSource(160, 120, fps=30, frames=30), "slow": SyntheticSource(64, 48, fps=10, frames=5)}
    t0 = time.monotonic()
    s = run_pipeline(tiny("thread"), sources, tmp_path / "o", progress=False)
    assert s["pace"] == "realtime" and time.monotonic() - t0 >= 0.9  # 30 frames at 30 Hz: paced, not rushed
    assert s["cameras"]["fast"]["frames_submitted"] == 30 and s["cameras"]["slow"]["frames_submitted"] == 5
    fm = s["cameras"]["slow"]["models"]["foundation"]
    assert fm["runs"] + fm["skipped"] == 5


def test_predict_draws_every_cameras_pictures_in_a_folder_of_its_own(tmp_path, folder, capsys):
    out = tmp_path / "pred"
    assert cli(["predict", "front=synthetic:320x240@30:2", f"rear={folder}", "-o", str(out), "--no-progress",
                "--exist-ok", "--mode", "thread"]) == 0  # fmt: skip
    assert sorted(p.name for p in (out / "front").iterdir()) == ["000000.jpg", "000001.jpg"]
    assert sorted(p.name for p in (out / "rear").iterdir()) == [f"im{i}.jpg" for i in range(4)]
    s = json.loads((out / "summary.json").read_text())
    assert s["cameras"]["rear"]["frames_submitted"] == 4


def test_a_config_with_other_cameras_is_refused_naming_both(tmp_path, capsys):
    cfg = tmp_path / "two.yaml"
    cfg.write_text("cameras: [{name: left}, {name: right}]\nheads: [{name: depth, model: tiny_depth}]\n")
    assert cli(["run", "-c", str(cfg), "-s", "front=synthetic:64x64@30:2", "-s", "rear=synthetic:64x64@30:2"]) == 1
    err = capsys.readouterr().err
    assert "the sources are named ['front', 'rear'] but the config's cameras are ['left', 'right']" in err
    assert cli(["run", "-c", str(cfg), "-s", "synthetic:64x64@30:2"]) == 1
    assert "the config has cameras ['left', 'right']: give one of the sources for each" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------------------- bags
def write_two_camera_bag(path) -> dict[str, list[tuple[int, int]]]:
    """A bag with a front (160x120) and a rear (200x90) image topic, 3 frames each, and the stamps it holds."""
    from rosbags.rosbag2 import Writer

    from vpengine.ros2.rosbags_msgs import typestore

    ts = typestore("jazzy")
    T = ts.types
    stamps: dict[str, list[tuple[int, int]]] = {"front": [], "rear": []}
    with Writer(path, version=9) as w:
        conns = {c: w.add_connection(f"/{c}/image_raw", "sensor_msgs/msg/Image", typestore=ts) for c in stamps}
        for i in range(3):
            for k, (camera, (h, wd)) in enumerate((("front", (120, 160)), ("rear", REAR_HW))):
                sec, nsec = 100 + i, 1000 * k + 7
                header = T["std_msgs/msg/Header"](
                    stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=f"{camera}_optical"
                )
                msg = T["sensor_msgs/msg/Image"](
                    header=header, height=h, width=wd, encoding="bgr8", is_bigendian=0, step=wd * 3,
                    data=frame(10 * k + i, h, wd).reshape(-1),
                )  # fmt: skip
                w.write(conns[camera], sec * 10**9 + nsec, ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))
                stamps[camera].append((sec, nsec))
    return stamps


def test_a_bag_with_two_image_topics_in_gives_each_cameras_outputs_under_its_namespace(tmp_path):
    from rosbags.rosbag2 import Reader

    from vpengine.ros2.rosbags_msgs import typestore

    src, dst = tmp_path / "in", tmp_path / "out"
    stamps = write_two_camera_bag(src)
    assert cli(["run", "-c", "tiny", "--mode", "thread", "--no-progress", "-s", str(src), "--topic",
                "front=/front/image_raw", "--topic", "rear=/rear/image_raw", "--out-bag", str(dst),
                "--set", "heads.seg.cameras=[rear]"]) == 0  # fmt: skip
    ts = typestore("jazzy")
    got: dict[str, list] = {}
    with Reader(dst) as r:
        for c, _, raw in r.messages():
            got.setdefault(c.topic, []).append(ts.deserialize_cdr(raw, c.msgtype))
    assert sorted(got) == [
        "/vpengine/front/depth/depth", "/vpengine/front/det/detections", "/vpengine/front/input/compressed",
        "/vpengine/rear/depth/depth", "/vpengine/rear/det/detections", "/vpengine/rear/input/compressed",
        "/vpengine/rear/seg/classes",
    ]  # fmt: skip
    for camera, (h, w) in (("front", (120, 160)), ("rear", REAR_HW)):
        depth = got[f"/vpengine/{camera}/depth/depth"]
        assert [(m.header.stamp.sec, m.header.stamp.nanosec) for m in depth] == stamps[camera]  # its own headers
        assert {(m.header.frame_id, m.width, m.height) for m in depth} == {(f"{camera}_optical", w, h)}
    seg = got["/vpengine/rear/seg/classes"]
    assert len(seg) == 3 and {(m.width, m.height) for m in seg} == {(200, 90)}


# ---------------------------------------------------------------------------------------------------------- ROS 2
@pytest.mark.xdist_group("dds")  # one DDS test at a time: no two share a domain or ports
def test_the_dds_bridge_takes_a_topic_per_camera_and_publishes_under_each_cameras_namespace(monkeypatch):
    """The bridge in this process (thread-mode engine) on loopback: two cameras of different sizes, each on its
    own topic; every output under ``<ns>/<camera>/`` with that camera's header and size."""
    import os

    from vpengine.ros2 import cdr
    from vpengine.ros2 import dds_types as T
    from vpengine.ros2.bridge import BridgeOptions, Ros2Bridge
    from vpengine.ros2.core import Ros2Core
    from vpengine.ros2.dds import DdsContext, loopback_config
    from vpengine.ros2.messages import Header
    from vpengine.ros2.outputs import image_out

    domain = 20 + (os.getpid() * 31 + int(time.time() * 1000)) % 200
    monkeypatch.setenv("CYCLONEDDS_URI", loopback_config())  # this process's own participants stay on loopback
    core = Ros2Core(tiny("thread"), namespace="/vp", cameras=["front", "rear"], overrides=["heads.seg.cameras=[rear]"])
    opts = BridgeOptions(
        {"front": "/front/image", "rear": "/rear/image"}, input_qos="default", domain_id=domain,
        dds_config=loopback_config(),
    )  # fmt: skip
    images = ["/vp/front/depth/depth", "/vp/rear/depth/depth", "/vp/rear/seg/classes"]
    assert {t.topic for t in core.topics} == {*images, "/vp/front/det/detections", "/vp/rear/det/detections"}
    with Ros2Bridge(core, opts):
        ctx = DdsContext(domain)
        try:
            writers = {c: ctx.writer(f"/{c}/image", T.Image_, "default") for c in ("front", "rear")}
            readers = {t: ctx.reader(t, T.Image_) for t in images}
            deadline = time.monotonic() + 30
            while not all(w.matched() for w in writers.values()) or not all(
                r.dds.get_matched_publications() for r in readers.values()
            ):
                assert time.monotonic() < deadline, "the bridge's topics never matched"
                time.sleep(0.05)
            writers["front"].write_raw(cdr.encode_image(image_out(frame(1, 240, 320), "bgr8", Header(10, 1, "f"))))
            writers["rear"].write_raw(cdr.encode_image(image_out(frame(2, *REAR_HW), "bgr8", Header(20, 2, "r"))))
            got = {}
            while len(got) < len(readers) and time.monotonic() < deadline:
                for topic, r in readers.items():
                    r.wait(0.05)
                    for raw in r.take_raw(4):
                        v = cdr.decode_image(raw)
                        got[topic] = (v.header, v.width, v.height)
        finally:
            ctx.close()
    assert got == {
        "/vp/front/depth/depth": (Header(10, 1, "f"), 320, 240),
        "/vp/rear/depth/depth": (Header(20, 2, "r"), 200, 90),
        "/vp/rear/seg/classes": (Header(20, 2, "r"), 200, 90),
    }
    assert core.camera_counters["front"]["submitted"] == core.camera_counters["rear"]["submitted"] == 1


# ------------------------------------------------------------------------------------------------------ live view
def test_the_live_view_serves_pictures_and_per_camera_stats_of_a_two_camera_run():
    """``--serve`` on a run of two cameras: each head's newest picture, drawn on its own camera's frame."""
    import re
    import shutil
    import subprocess
    import sys
    import urllib.request

    from tests_paths import ROOT

    exe = shutil.which("vpengine", path=str(ROOT / ".venv" / "bin")) or shutil.which("vpengine")
    cmd = [exe] if exe else [sys.executable, "-m", "vpengine.cli.main"]
    cmd += ["run", "-c", "tiny", "--mode", "thread", "--no-progress", "--serve", "0",
            "-s", "front=synthetic:160x120@30:300", "-s", "rear=synthetic:160x120@15:150"]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = None
        while url is None and (line := proc.stderr.readline()):
            m = re.search(r"live view at (http://\S+)", line)
            url = m and m.group(1)
        assert url, "no live view line"
        deadline = time.monotonic() + 60
        while True:
            try:
                with urllib.request.urlopen(url + "api/stats", timeout=10) as r:
                    stats = json.loads(r.read())
                with urllib.request.urlopen(url + "api/latest/seg.jpg", timeout=10) as r:
                    if r.status == 200:
                        on_frame = r.headers["X-On-Frame"]
                        break
            except OSError:
                pass
            assert time.monotonic() < deadline, "no seg picture within 60 s"
            time.sleep(0.2)
        assert on_frame == "1" and set(stats["cameras"]) == {"front", "rear"}
    finally:
        proc.kill()
        proc.wait()
