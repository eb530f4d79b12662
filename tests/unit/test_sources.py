"""Frame sources. A camera is a stand-in capture the test hands frames to one at a time (Note [Live capture])."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest

from helpers.camera import FakeCamera
from vpengine.io.sources import VideoSource


def wait_until(cond: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


def camera_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "vpengine-camera"]


def test_a_loop_that_keeps_up_with_the_camera_gets_every_frame_in_order():
    cam = FakeCamera()
    src = VideoSource(0, capture=cam)
    assert src.live and (src.width, src.height, src.fps) == (8, 6, 30.0) and len(src) == 0
    it = iter(src)
    for k in range(6):
        cam.deliver()
        f = next(it)
        assert f.name == f"{k:06d}" and int(f.image[0, 0, 0]) == k and f.timestamp is not None
    assert src.missed == 0
    cam.end_at = cam.i  # unplugged: the frames end
    cam.deliver()
    assert list(it) == []
    wait_until(lambda: not camera_threads())


def test_a_slow_loop_takes_the_newest_frame_and_counts_the_ones_it_replaced():
    cam = FakeCamera()
    src = VideoSource(0, capture=cam)
    it = iter(src)
    cam.deliver()
    assert next(it).name == "000000"  # the reader thread runs from here on
    cam.deliver(5)  # five frames come while the loop is busy
    wait_until(lambda: src.missed == 4)
    f = next(it)
    assert f.name == "000005" and int(f.image[0, 0, 0]) == 5  # the newest, not the oldest queued
    cam.deliver()
    assert next(it).name == "000006" and src.missed == 4
    cam.end_at = cam.i
    cam.deliver()
    assert list(it) == []
    wait_until(lambda: not camera_threads())


def test_the_camera_ending_ends_the_frames_after_the_newest_and_every_frame_is_taken_or_counted():
    cam = FakeCamera(end_at=9)
    src = VideoSource(0, capture=cam)
    cam.deliver(10)  # nine frames, then the end
    frames = list(src)
    ids = [int(f.name) for f in frames]
    assert ids == sorted(set(ids)) and ids[-1] == 8 and len(ids) + src.missed == 9
    wait_until(lambda: not camera_threads())


def test_a_camera_that_fails_raises_naming_it_and_stopping_early_stops_its_reader():
    cam = FakeCamera(fail_at=2)
    cam.deliver(3)
    with pytest.raises(RuntimeError, match=r"reading camera 0 failed: OSError\('device unplugged'\)"):
        list(VideoSource(0, capture=cam))
    wait_until(lambda: not camera_threads())

    cam = FakeCamera()
    it = iter(VideoSource(0, capture=cam))
    cam.deliver()
    next(it)
    it.close()  # type: ignore[attr-defined]  # waits up to 1 s for the read in progress
    cam.deliver()  # which returns with the camera's next frame, and the reader stops there
    wait_until(lambda: not camera_threads())
    assert cam.i == 2
