"""Live sources through OpenCV: V4L2 cameras (``camera:N``, a device path such as ``/dev/video0`` or
``/dev/v4l/by-id/...``), network streams (``rtsp://``, ``rtsps://``, ``http://``, ``https://``, ``udp://``... read by
FFmpeg) and GStreamer pipelines (``gst:PIPELINE``, or a pipeline that ends in ``appsink`` as it is).

Opening checks what can be checked before OpenCV is asked (the device file, the backend), then opens with a timeout
and reads one frame, so a source that cannot work is refused before the engine starts, in one line that names what
failed and why, with any password in it masked (Note [Redacting] in vpengine/redact.py).
:func:`vpengine.io.sources.open_source` then reads the frames with a ``VideoSource``, on its
capture thread, newest frame wins (Note [Live capture]). A network stream that has a length (a video file on a web
server) is read as a file: every frame, on the video's own timeline.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import stat
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vpengine.io.stderr import captured_stderr
from vpengine.redact import redact

log = logging.getLogger("vpengine.sources")

#: Seconds a stream or pipeline may take to open, and then to deliver each frame, before it is given up (OpenCV's
#: V4L2 backend has its own wait for a camera, 10 s). Long enough for an RTSP camera's first keyframe.
TIMEOUT_S = 10.0
#: The character-device major number of every video4linux device (Linux's VIDEO_MAJOR).
_VIDEO_MAJOR = 81
_URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")
# V4L2's names; other paths under /dev (say a folder of frames in /dev/shm) are files like any other
_V4L2_PATH = re.compile(r"^/dev/(video\d|v4l)")
_GST_PREFIX = "gst:"


@dataclass
class Opened:
    """A live source's capture, open and checked: it has delivered ``image`` (at ``stamp`` seconds of its own
    timeline, for a stream with a length). ``path`` is what it was opened as (an int for a camera index), ``what`` how
    messages name it, ``live`` False for a stream with a length (a video file on a web server, read as a file), and
    ``read_timeout`` the seconds the capture waits for a frame before it gives up (None: the driver's own)."""

    path: str | int
    capture: Any
    what: str
    image: np.ndarray
    stamp: float
    live: bool = True
    read_timeout: float | None = None


def is_live(spec: str) -> bool:
    """True for a spec this module opens: ``camera:N``, a V4L2 device path (``/dev/videoN``, ``/dev/v4l/...``) or
    any character device, a URL (``scheme://...``), ``gst:PIPELINE`` or a bare GStreamer pipeline (``... ! appsink``)."""
    return (
        spec.startswith(("camera:", _GST_PREFIX))
        or bool(_URL.match(spec) or _V4L2_PATH.match(spec))
        or _bare_pipeline(spec)
        or _char_device(Path(spec))
    )


def open_live(spec: str, timeout: float | None = None) -> Opened:
    """The capture of a live spec (:func:`is_live`), opened and checked: it has delivered one frame. ``timeout``:
    seconds a stream may take to open and each frame to come (default :data:`TIMEOUT_S`). ValueError, one line,
    naming what failed and why, when it cannot be read. Any other spec is taken as a device path."""
    try:
        return _open_live(spec, TIMEOUT_S if timeout is None else timeout)
    except ValueError as e:  # whatever the message quotes (the spec, OpenCV's words) goes out without its secrets
        raise ValueError(redact(str(e))) from None


def _open_live(spec: str, timeout: float) -> Opened:
    if spec.startswith("camera:"):
        index = spec.split(":", 1)[1]
        if not index.isdigit():
            raise ValueError(f"bad camera source {spec!r}; use camera:N with N the camera's index, e.g. camera:0")
        return _open_camera(int(index))
    if spec.startswith(_GST_PREFIX) or _bare_pipeline(spec):
        pipeline = spec[len(_GST_PREFIX) :].strip() if spec.startswith(_GST_PREFIX) else spec
        return _open_pipeline(pipeline, timeout)
    if _URL.match(spec):
        return _open_stream(spec, timeout)
    return _open_device(Path(spec), spec)


# --------------------------------------------------------------------------------------------------------- cameras
def _open_camera(index: int) -> Opened:
    if not sys.platform.startswith("linux"):  # no device files to check: OpenCV's index is all there is
        cap, _ = _attempt(lambda cv2: cv2.VideoCapture(index))
        if cap is None:
            raise ValueError(f"no camera {index}: OpenCV found none at index {index}")
        return _probed(cap, index, f"camera {index}")
    device = Path(f"/dev/video{index}")
    if not device.exists():
        raise ValueError(f"no camera {index}: {device} does not exist ({_video_devices()})")
    return _open_device(device, f"camera:{index}", index)


def _open_device(device: Path, spec: str, index: int | None = None) -> Opened:
    what = f"camera {spec!r}" if index is None else f"camera {index} ({device})"
    if not device.exists():
        raise ValueError(f"no such device {spec!r}: the path does not exist ({_video_devices()})")
    mode = device.stat().st_mode
    if not stat.S_ISCHR(mode):
        kind = "a folder" if stat.S_ISDIR(mode) else "a file"
        raise ValueError(f"{spec!r} is not a device: it is {kind}, and a camera is a character device (/dev/videoN)")
    if not os.access(device, os.R_OK | os.W_OK):
        raise ValueError(f"cannot open {what}: permission denied{_group_hint(device)}")
    cv2 = _cv2()
    if not _has_backend(cv2, "CAP_V4L2"):
        raise ValueError(f"cannot open {what}: this OpenCV ({_opencv()}) has no V4L2 backend")
    cap, _ = _attempt(lambda cv2: cv2.VideoCapture(str(device), cv2.CAP_V4L2))
    if cap is None:
        major = os.major(device.stat().st_rdev)
        why = (
            "busy (another program has it?) or not a capture device"
            if major == _VIDEO_MAJOR
            else f"not a video device (device {major}:{os.minor(device.stat().st_rdev)}; video devices are "
            f"{_VIDEO_MAJOR}:N)"
        )
        raise ValueError(f"cannot open {what}: {why}")
    return _probed(cap, index if index is not None else spec, what)


def _video_devices() -> str:
    found = sorted(str(p) for p in Path("/dev").glob("video*"))
    return f"video devices here: {', '.join(found)}" if found else "there are no video devices here"


def _group_hint(device: Path) -> str:
    try:
        import grp

        group = grp.getgrgid(device.stat().st_gid).gr_name
    except (ImportError, KeyError):
        return ""
    if group == "root":  # joining root's group is no advice to give
        return " (only root may open it; a udev rule can give it to the group 'video')"
    return f" (it belongs to group '{group}': sudo usermod -aG {group} $USER, then log in again)"


def _char_device(path: Path) -> bool:
    try:
        return stat.S_ISCHR(path.stat().st_mode)
    except (OSError, ValueError):
        return False


# --------------------------------------------------------------------------------------------- streams, pipelines
def _open_stream(url: str, timeout: float) -> Opened:
    what = f"stream {redact(url)!r}"
    cv2 = _cv2()
    if not _has_backend(cv2, "CAP_FFMPEG"):
        raise ValueError(
            f"cannot open {what}: this OpenCV ({_opencv()}) has no FFMPEG backend (opencv-python from PyPI has "
            "one), or read it with a gst: pipeline"
        )
    why = "no video there (refused, not found, or not a format FFmpeg reads)"
    cap, read_timeout = _open_timed(url, cv2.CAP_FFMPEG, what, timeout, why)
    frames = cap.get(cv2.CAP_PROP_FRAME_COUNT)
    remote_file = math.isfinite(frames) and frames > 0  # a live stream has no length
    return _probed(cap, url, what, live=not remote_file, read_timeout=read_timeout)


def _open_pipeline(pipeline: str, timeout: float) -> Opened:
    what = f"GStreamer pipeline {redact(pipeline)!r}"
    cv2 = _cv2()
    if not _has_backend(cv2, "CAP_GSTREAMER"):
        raise ValueError(
            f"cannot open {what}: this OpenCV ({_opencv()}) has no GStreamer backend; use an OpenCV built with "
            "GStreamer (e.g. the system's python3-opencv), or give the stream's URL or device instead"
        )
    why = "GStreamer refused it (does it end in appsink? try it with gst-launch-1.0)"
    cap, read_timeout = _open_timed(pipeline, cv2.CAP_GSTREAMER, what, timeout, why)
    return _probed(cap, pipeline, what, read_timeout=read_timeout)


def _open_timed(target: str, api: int, what: str, timeout: float, refused: str) -> tuple[Any, float | None]:
    """(a capture of ``target`` through backend ``api``, opened within ``timeout`` s; the read timeout it has, None
    for none: Note [Timeouts on older OpenCV]); ValueError naming why not (what OpenCV or FFmpeg said, else
    ``refused``).

    Note [Timeouts on older OpenCV]: FFmpeg's backend honours the open and read timeouts since OpenCV 4.5.2 (the
    properties came with it), GStreamer's only since 4.7, and Ubuntu's and JetPack 5's OpenCV are older. A backend
    that does not know a parameter refuses the whole open ("unsupported parameters in .open() ... Bailout"), so a
    quick refusal is tried once more without the timeouts, unless FFmpeg got as far as saying why it failed (then
    it took them). Opened that way, a read waits as long as the backend
    does: a stream that stops may hang the run instead of ending its source."""
    cv2 = _cv2()
    ms = int(timeout * 1000)
    keys = getattr(cv2, "CAP_PROP_OPEN_TIMEOUT_MSEC", None), getattr(cv2, "CAP_PROP_READ_TIMEOUT_MSEC", None)
    said: list[str] = []
    if None not in keys:
        t0 = time.monotonic()
        cap, said = _attempt(lambda cv2: cv2.VideoCapture(target, api, [keys[0], ms, keys[1], ms]))
        if cap is not None:
            return cap, timeout
        if time.monotonic() - t0 >= 0.9 * timeout:
            raise ValueError(f"cannot open {what}: it did not answer within {timeout:g} s")
        if _ffmpeg_error(said):
            raise ValueError(f"cannot open {what}: {_because(said)}")
    cap, said = _attempt(lambda cv2: cv2.VideoCapture(target, api))
    if cap is None:  # the first refusal's words may be only about the parameters: this one's are the reason
        raise ValueError(f"cannot open {what}: {_because(said) or refused}")
    log.debug(
        "%s: opened without timeouts, which this OpenCV (%s) does not take there; its reads have no timeout",
        what,
        _opencv(),
    )
    return cap, None


def _bare_pipeline(spec: str) -> bool:
    return "!" in spec and spec.rstrip().split("!")[-1].split()[0:1] == ["appsink"]


# ------------------------------------------------------------------------------------------------ opening, probing
def _probed(cap: Any, path: str | int, what: str, live: bool = True, read_timeout: float | None = None) -> Opened:
    """``cap`` once it has delivered a frame; ValueError, after releasing it, if it gives none."""
    t0 = time.monotonic()
    with _quiet() as said:
        ok, img = cap.read()
        stamp = cap.get(_cv2().CAP_PROP_POS_MSEC) / 1000.0 if ok else 0.0
    if not ok or img is None or img.size == 0:
        cap.release()
        if read_timeout is not None and time.monotonic() - t0 >= 0.9 * read_timeout:
            raise ValueError(f"{what} opened but sent no frame within {read_timeout:g} s")
        why = _because(said)
        raise ValueError(f"{what} opened but gave no frame" + (f" ({why})" if why else ""))
    return Opened(path, cap, what, np.ascontiguousarray(img), stamp, live, read_timeout)


def _attempt(make: Callable[[Any], Any]) -> tuple[Any, list[str]]:
    """(the capture ``make`` opened, or None; what OpenCV said meanwhile)."""
    cv2 = _cv2()
    # an OpenCV without the overload that takes parameters raises TypeError; one in exception mode, cv2.error
    refusals = (TypeError, getattr(cv2, "error", TypeError))
    with _quiet() as said:
        try:
            cap = make(cv2)
        except refusals as e:
            cap = None
            log.debug("opencv refused: %s", redact(str(e)))
        else:
            if not cap.isOpened():
                cap.release()
                cap = None
    return cap, said


@contextlib.contextmanager
def _quiet() -> Iterator[list[str]]:
    """Note [OpenCV's chatter]: while a capture opens, OpenCV writes a WARN line for each backend it tries and fails
    with, and FFmpeg its own errors, to descriptor 2. For the open and the first read, and only then, they are
    captured (Note [Borrowing stderr] in io/stderr.py, which says what that costs other threads): the lines come
    back in the list, are logged at DEBUG without their secrets (``vpengine -vv`` shows them), and
    :func:`_because` makes the refusal's reason of them. The CLI opens its sources before anything else runs."""
    with captured_stderr() as said:
        yield said
    for line in said:
        log.debug("opencv: %s", redact(line))


# OpenCV's own log line: '[ WARN:0@0.01] global cap_gstreamer.cpp:1127 open OpenCV | GStreamer warning: ...'
# (before 4.6: '[ WARN:0] global /path/cap_gstreamer.cpp (711) open OpenCV | ...'); its tail is the reason
_OPENCV_LINE = re.compile(r"^\[\s*(?:WARN|ERROR)[^\]]*\]\s+\S+\s+\S+?(?::\d+| \(\d+\))\s+\S+\s+(.+)$")


def _because(said: list[str]) -> str:
    """A reason, from what OpenCV said, or "": the last FFmpeg error (``[tcp @ 0x...] Connection to ... failed:
    Connection refused`` gives ``Connection refused``), else OpenCV's first warning or error that says something
    (``Error opening bin: no element "foo"``)."""
    ffmpeg = _ffmpeg_error(said)
    if ffmpeg:
        return redact(ffmpeg.rsplit("failed: ", 1)[-1])
    for line in said:
        m = _OPENCV_LINE.match(line.strip())
        if m and "can't be used to capture by name" not in m.group(1):  # the backend list, not the reason
            return redact(m.group(1).split("GStreamer warning: ", 1)[-1])
    return ""


def _ffmpeg_error(said: list[str]) -> str:
    """The last line FFmpeg wrote (``[tcp @ 0x55d0...] Connection to ... failed``), without its prefix, or ""."""
    for line in reversed(said):
        m = re.match(r"^\[[^\]@]+ @ 0x[0-9a-fA-F]+\] (.+)$", line.strip())
        if m:
            return m.group(1)
    return ""


def _cv2() -> Any:
    import cv2

    return cv2


def _has_backend(cv2: Any, name: str) -> bool:
    return bool(cv2.videoio_registry.hasBackend(getattr(cv2, name)))


def _opencv() -> str:
    return str(_cv2().__version__)
