"""Live sources (vpengine.io.live): devices by path, network streams and GStreamer pipelines. No camera here: the
refusals are checked on what this machine has, and the streams are real ones served on 127.0.0.1."""

from __future__ import annotations

import os
import tempfile
import threading
import time
from pathlib import Path

import pytest

from helpers.streams import FileServer, MjpegCamera, SilentServer, closed_port
from vpengine.io import live
from vpengine.io.sources import SAMPLES, open_source

pytestmark = pytest.mark.timeout(120)


def refusal(spec: str, capfd: pytest.CaptureFixture[str]) -> str:
    """The one-line error opening ``spec`` gives; OpenCV and FFmpeg said nothing on the terminal meanwhile."""
    capfd.readouterr()
    with pytest.raises(ValueError) as e:
        open_source(spec)
    out, err = capfd.readouterr()
    assert (out, err) == ("", ""), "OpenCV spoke on the terminal"
    assert "\n" not in str(e.value)
    return str(e.value)


def no_device(path: str) -> str:
    if os.path.exists(path):
        pytest.skip(f"{path} exists on this machine")
    return path


def test_a_missing_device_or_camera_is_no_such_device_not_a_codec_error(capfd):
    dev = no_device("/dev/video97")
    assert refusal(dev, capfd).startswith("no such device '/dev/video97': the path does not exist (")
    assert refusal("camera:97", capfd).startswith("no camera 97: /dev/video97 does not exist (")
    by_id = "/dev/v4l/by-id/usb-No_Such_Camera-video-index0"
    assert refusal(by_id, capfd).startswith(f"no such device {by_id!r}: the path does not exist")
    assert "use camera:N" in refusal("camera:front", capfd)


def test_a_file_or_folder_given_as_a_device_and_a_device_that_is_not_video_are_refused(tmp_path, capfd):
    (tmp_path / "video0").write_bytes(b"")  # as ffmpeg leaves /dev/video0 when it writes to a missing loopback device
    for path, kind in [(tmp_path / "video0", "a file"), (tmp_path, "a folder")]:
        with pytest.raises(ValueError) as e:
            live.open_live(str(path))
        assert (
            str(e.value)
            == f"{str(path)!r} is not a device: it is {kind}, and a camera is a character device (/dev/videoN)"
        )
    assert refusal("/dev/null", capfd) == (
        "cannot open camera '/dev/null': not a video device (device 1:3; video devices are 81:N)"
    )
    assert capfd.readouterr() == ("", "")


def test_paths_under_dev_that_are_not_v4l2_names_are_files_like_any_other(tmp_path):
    if not os.access("/dev/shm", os.W_OK):
        pytest.skip("no writable /dev/shm")
    with tempfile.TemporaryDirectory(dir="/dev/shm", prefix="vpengine-test-") as d:
        assert not live.is_live(d) and live.is_live("/dev/video0") and live.is_live("/dev/v4l/by-id/x")
        with pytest.raises(ValueError, match="no images"):
            open_source(d)  # a folder of frames in RAM, not a camera


def test_a_device_the_user_may_not_open_says_permission_denied_and_which_group_to_join(capfd, monkeypatch):
    monkeypatch.setattr(live.os, "access", lambda path, mode: False)  # as a user outside the device's group
    msg = refusal("/dev/null", capfd)
    assert msg.startswith("cannot open camera '/dev/null': permission denied (")
    assert "group" in msg


@pytest.mark.parametrize("spec", ["gst:videotestsrc ! videoconvert ! appsink", "videotestsrc ! appsink drop=true"])
def test_a_gstreamer_pipeline_on_an_opencv_without_gstreamer_says_so(spec, capfd):
    import cv2

    if cv2.videoio_registry.hasBackend(cv2.CAP_GSTREAMER):
        pytest.skip("this OpenCV has GStreamer")
    assert "has no GStreamer backend" in refusal(spec, capfd)


@pytest.mark.parametrize("scheme", ["rtsp", "http", "rtsps"])
def test_a_stream_on_a_closed_port_is_refused_at_once_in_one_line(scheme, capfd):
    url = f"{scheme}://user:secret@127.0.0.1:{closed_port()}/live"
    t0 = time.monotonic()
    msg = refusal(url, capfd)
    assert time.monotonic() - t0 < live.TIMEOUT_S  # refused, not waited out
    assert msg == f"cannot open stream '{scheme}://user:***@127.0.0.1:{url.split(':')[-1]}': Connection refused"


def test_a_stream_that_does_not_answer_is_given_up_after_the_timeout(capfd, monkeypatch):
    monkeypatch.setattr(live, "TIMEOUT_S", 1.0)
    with SilentServer() as server:
        t0 = time.monotonic()
        msg = refusal(f"http://127.0.0.1:{server.port}/cam", capfd)
    assert msg == f"cannot open stream 'http://127.0.0.1:{server.port}/cam': it did not answer within 1 s"
    assert time.monotonic() - t0 < 30


def camera_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "vpengine-camera"]


def wait_until(cond, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_an_http_camera_is_read_live_newest_frame_first_and_closing_stops_its_reader():
    with MjpegCamera(width=64, height=48, fps=50) as cam, open_source(cam.url) as src:
        assert src.live and (src.width, src.height) == (64, 48) and len(src) == 0
        it = iter(src)
        frames = [next(it) for _ in range(3)]
        assert all(f.image.shape == (48, 64, 3) for f in frames)
        assert [f.timestamp for f in frames] == sorted(f.timestamp for f in frames)
        time.sleep(0.5)  # a busy loop: the camera goes on meanwhile
        later = next(it)
        assert src.missed > 0 and int(later.name) > int(frames[-1].name) + 1  # the newest, not the next queued
        # the run ends without closing its iterator: close() stops the reader before it frees the capture
    wait_until(lambda: not camera_threads())


def test_a_stream_that_hangs_or_closes_mid_run_ends_the_source_with_a_warning(caplog, monkeypatch):
    caplog.set_level("WARNING", logger="vpengine.sources")
    monkeypatch.setattr(live, "TIMEOUT_S", 1.0)
    with MjpegCamera(stall_after=4) as cam, open_source(cam.url) as src:
        frames = list(src)  # ends: the read gives up after 1 s
    assert 0 < len(frames) <= 3  # the first was the check at opening
    assert f"stream '{cam.url}' ended after " in caplog.text and "no frame came for 1 s" in caplog.text
    caplog.clear()
    with MjpegCamera(close_after=4) as cam, open_source(cam.url) as src:
        list(src)
    assert f"stream '{cam.url}' ended after " in caplog.text and "it stopped delivering" in caplog.text
    wait_until(lambda: not camera_threads())


def test_a_video_file_on_a_web_server_is_read_as_a_file_every_frame_on_its_timeline():
    with FileServer(Path(SAMPLES)) as server, open_source(server.url + "street.mp4") as src:
        assert not src.live and (src.width, src.height, src.fps, len(src)) == (768, 576, 10.0, 50)
        frames = list(src)
    assert len(frames) == 50 and [f.name for f in frames[:2]] == ["000000", "000001"]
    assert [f.timestamp for f in frames[:3]] == pytest.approx([0.0, 0.1, 0.2])
    assert all(f.image.shape == (576, 768, 3) for f in frames)
    with FileServer(Path(SAMPLES)) as server, pytest.raises(ValueError, match="cannot open stream .*nope.mp4'"):
        open_source(server.url + "nope.mp4")


def test_a_stream_that_opens_but_gives_no_frame_says_so(capfd):
    with FileServer(Path(SAMPLES), ranges=False) as server:  # the sample's index is at its end: out of reach
        msg = refusal(server.url + "street.mp4", capfd)
    assert msg.startswith(f"stream '{server.url}street.mp4' opened but gave no frame")


# ------------------------------------------------------------------------------------- secrets (Note [Redacting])
SECRETS = ("p@ss", "hunter2", "tok3n")


def with_secrets(url: str) -> str:
    """``url`` (http://127.0.0.1:PORT/PATH) with a password holding an '@' and a token in its query."""
    return url.replace("http://", "http://admin:p@ss@", 1) + "?user=admin&token=tok3n"


def test_a_stream_with_credentials_keeps_them_out_of_its_refusal_its_warnings_and_its_debug_log(capfd, caplog):
    caplog.set_level("DEBUG", logger="vpengine.sources")
    msg = refusal(with_secrets(f"http://127.0.0.1:{closed_port()}/live"), capfd)
    assert msg.startswith("cannot open stream 'http://admin:***@127.0.0.1:") and msg.endswith(
        "/live?user=admin&token=***': Connection refused"
    )
    with MjpegCamera(close_after=4) as cam, open_source(with_secrets(cam.url)) as src:
        assert src.what == f"stream 'http://admin:***@127.0.0.1:{cam.port}/cam?user=admin&token=***'"
        list(src)
    assert f"{src.what} ended after " in caplog.text
    assert not [s for s in SECRETS if s in msg + caplog.text]


def test_the_run_summary_names_a_stream_without_its_password(tmp_path):
    from tests_paths import tiny
    from vpengine.pipeline.run import run_pipeline

    with MjpegCamera(width=64, height=48, fps=30) as cam, open_source(with_secrets(cam.url)) as src:
        summary = run_pipeline(tiny("thread"), src, out_dir=tmp_path, max_frames=2, progress=False, folder=False)
    written = (tmp_path / "summary.json").read_text()
    assert summary["source"] == f"http://admin:***@127.0.0.1:{cam.port}/cam?user=admin&token=***"
    assert summary["source"] in written and not [s for s in SECRETS if s in written]


# what OpenCV 4.5 writes to descriptor 2 when its GStreamer backend is given parameters, and for a missing element
BAILOUT = (
    b"[ERROR:0] global cap_gstreamer.cpp (1234) open VIDEOIO/GStreamer: unsupported parameters in .open(), "
    b"see logger INFO channel for details. Bailout\n"
)
NO_ELEMENT = (
    b"[ WARN:0] global /build/cap_gstreamer.cpp (711) open OpenCV | GStreamer warning: "
    b'Error opening bin: no element "nosuchsrc"\n'
    b"[ WARN:0] global /build/cap_gstreamer.cpp (480) isPipelinePlaying OpenCV | GStreamer warning: GStreamer: "
    b"pipeline have not been created\n"
)


class OldOpenCV:
    """cv2 as an OpenCV whose GStreamer backend takes no timeouts (before 4.7; Ubuntu's, JetPack 5's): an open with
    parameters is refused, as OpenCV does, with its ERROR line on descriptor 2 (``how='bailout'``), or raises
    TypeError (``how='no overload'``: before 4.5.2). Without parameters a pipeline opens, unless it names an element
    GStreamer does not have."""

    CAP_GSTREAMER, CAP_FFMPEG, CAP_PROP_POS_MSEC = 1800, 1900, 0
    CAP_PROP_OPEN_TIMEOUT_MSEC, CAP_PROP_READ_TIMEOUT_MSEC = 53, 54
    __version__ = "4.5.4"
    error = RuntimeError

    def __init__(self, how: str) -> None:
        self.opened: list[tuple[str, list[int] | None]] = []
        self.videoio_registry = self

        fake = self

        class Capture:
            def __init__(self, target: str, api: int, params: list[int] | None = None) -> None:
                fake.opened.append((target, params))
                self.ok = True
                if params is not None:
                    if how == "no overload":
                        raise TypeError("VideoCapture() takes at most 2 arguments (3 given)")
                    os.write(2, BAILOUT)
                    self.ok = False
                elif "nosuchsrc" in target:
                    os.write(2, NO_ELEMENT)
                    self.ok = False

            def isOpened(self) -> bool:
                return self.ok

            def read(self):
                import numpy as np

                return True, np.zeros((4, 6, 3), np.uint8)

            def get(self, prop: int) -> float:
                return 0.0

            def release(self) -> None:
                pass

        self.VideoCapture = Capture

    def hasBackend(self, api: int) -> bool:
        return True


@pytest.mark.parametrize("how", ["bailout", "no overload"])
def test_a_pipeline_on_an_opencv_whose_gstreamer_takes_no_timeouts_opens_without_them(how, monkeypatch, capfd, caplog):
    cv2 = OldOpenCV(how)
    monkeypatch.setattr(live, "_cv2", lambda: cv2)
    caplog.set_level("DEBUG", logger="vpengine.sources")
    capfd.readouterr()
    o = live.open_live("gst:videotestsrc ! videoconvert ! appsink")
    assert [p is None for _, p in cv2.opened] == [False, True]  # with the timeouts, then once without
    assert o.read_timeout is None and o.image.shape == (4, 6, 3)  # reads wait as long as GStreamer does
    assert "opened without timeouts" in caplog.text and "its reads have no timeout" in caplog.text
    assert capfd.readouterr() == ("", "")


def test_a_pipeline_an_old_opencv_refuses_says_gstreamers_reason_without_secrets(monkeypatch, capfd):
    monkeypatch.setattr(live, "_cv2", lambda: OldOpenCV("bailout"))
    msg = refusal("nosuchsrc location=rtsp://admin:p@ss@cam/h264 user-pw=hunter2 ! appsink", capfd)
    assert msg == (
        "cannot open GStreamer pipeline 'nosuchsrc location=rtsp://admin:***@cam/h264 user-pw=*** ! appsink': "
        'Error opening bin: no element "nosuchsrc"'
    )
