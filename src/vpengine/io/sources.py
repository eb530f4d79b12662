"""Frame sources: a built-in synthetic scene, images (a file, a folder, a glob), video files, cameras and streams
(opened by io/live.py), rosbag2 bags (io/bag.py) and the samples that ship with the package (``sample:street``,
``sample:cheetah``).

Every source yields :class:`~vpengine.io.base.Frame` objects: an HxWx3 uint8 image in the source's channel order
(OpenCV order, BGR, for everything here) at its own size, and a capture timestamp in seconds. Files are stamped on
their own timeline (a video by each frame's position, images at ``i / fps``), so rate limits are judged by the
source's clock, not by how fast the files are read; cameras by the time a frame arrived.
"""

from __future__ import annotations

import glob
import logging
import math
import re
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

from vpengine.io.base import Frame, Source
from vpengine.redact import redact

log = logging.getLogger("vpengine.sources")

#: The sample media shipped with the package (see its README.md for origin and licences).
SAMPLES = Path(__file__).resolve().parents[1] / "samples"

IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"}
VIDEO_EXTS = {".avi", ".mp4", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg"}

#: Note [Short videos]: a video file whose frames end early (cut off by a copy or a download, damaged) reads like a
#: whole one: OpenCV's read just says there are no more frames. Its header's frame count (``CAP_PROP_FRAME_COUNT``)
#: tells the two apart, but only roughly: it is the container's count where it keeps one (AVI, MP4) and otherwise
#: the duration times the rate, rounded, which can be a frame or so off either way (rounding, a shorter last frame),
#: and a clip cut without re-encoding counts the frames before its first keyframe that the decoder drops. So a file
#: is short when it ends more than SHORT_VIDEO_SLACK frames and more than SHORT_VIDEO_SHARE of its count early; a
#: cut-off file ends far earlier. A variable-rate file, or a copy-cut clip of a long keyframe interval, can still be
#: further off: the warning says "may be", and a false alarm beats a truncated file passing in silence.
SHORT_VIDEO_SLACK = 2
SHORT_VIDEO_SHARE = 0.05


class SyntheticSource(Source):
    """Moving shapes on a gradient: deterministic, any size and rate, no files needed.

    ``synthetic``, ``synthetic:640x480``, ``synthetic:1920x1080@30`` or ``synthetic:640x480@30:300`` (frames).
    """

    _SPEC = re.compile(r"^synthetic(?::(\d+)x(\d+))?(?:@(\d+(?:\.\d*)?|\.\d+))?(?::(\d+))?$")

    def __init__(self, width: int = 640, height: int = 480, fps: float = 30.0, frames: int = 300, seed: int = 0):
        if width < 14 or height < 14:
            raise ValueError(f"synthetic source size {width}x{height} is too small (min 14x14)")
        fps = _positive_rate(fps, "synthetic source rate")
        self.width, self.height, self.fps, self.frames = width, height, fps, frames
        rng = np.random.default_rng(seed)
        self._shapes = [
            (
                rng.uniform(0.1, 0.9, 2),
                rng.uniform(-0.3, 0.3, 2),
                rng.uniform(0.04, 0.15),
                rng.integers(40, 255, 3),
            )
            for _ in range(6)
        ]
        yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
        self._bg = np.stack([xx / width * 120, yy / height * 120, np.full_like(xx, 60)], -1).astype(np.uint8)
        self._yy, self._xx = yy, xx

    @classmethod
    def parse(cls, spec: str) -> SyntheticSource:
        m = cls._SPEC.match(spec)
        if not m:
            raise ValueError(
                f"bad synthetic source {spec!r}; use synthetic[:WIDTHxHEIGHT][@FPS][:FRAMES], e.g. synthetic:640x480@30:300"
            )
        w, h, fps, n = m.groups()
        return cls(int(w or 640), int(h or 480), float(fps or 30.0), int(n or 300))

    def render(self, i: int) -> np.ndarray:
        img = self._bg.copy()
        t = i / self.fps
        s = min(self.width, self.height)
        for k, (p0, v, r, color) in enumerate(self._shapes):
            p = (p0 + v * t) % 1.0
            cx, cy, rad = p[0] * self.width, p[1] * self.height, r * s
            if k % 2:
                mask = (self._xx - cx) ** 2 + (self._yy - cy) ** 2 < rad**2
            else:
                mask = (np.abs(self._xx - cx) < rad) & (np.abs(self._yy - cy) < rad * 0.6)
            img[mask] = color
        return img

    def __len__(self) -> int:
        return self.frames

    @property
    def pace(self) -> Literal["lockstep", "realtime"]:
        return "realtime"  # it stands in for a camera, paced at its fps

    def __iter__(self) -> Iterator[Frame]:
        for i in range(self.frames):
            yield Frame(self.render(i), None, f"{i:06d}")


class ImageSource(Source):
    """Image files in a given order: a folder's images by name, a glob's matches, or a single image.

    Each image comes at its own size (a folder of mixed sizes is never stretched to one size); ``height`` and
    ``width`` are those of the first image. Frames are stamped on the source's own timeline, image ``i`` at
    ``i / fps`` seconds (30 Hz unless ``fps`` is given), so rate limits treat a folder like a camera at that rate.
    An image that cannot be read is skipped with a warning and listed in ``skipped`` (file and why); one that
    decodes only partly (a truncated JPEG or PNG, the rest filled in grey by the decoder) is used, with a warning,
    and listed in ``partial``."""

    def __init__(self, files: Sequence[str | Path], path: str | Path, fps: float | None = None) -> None:
        self.path = str(path)
        self.files = [Path(f) for f in files]
        if not self.files:
            raise ValueError(f"no images ({', '.join(sorted(IMAGE_EXTS))}) in {self.path!r}")
        self.fps = _positive_rate(fps, "image source rate") if fps is not None else 30.0
        stems = [f.stem for f in self.files]
        unique = len(set(stems)) == len(stems)  # a glob over several folders may repeat a name
        self.names = stems if unique else [f"{i:06d}_{s}" for i, s in enumerate(stems)]
        self.skipped: list[dict[str, str]] = []
        self.partial: list[str] = []
        self._first: tuple[int, np.ndarray] | None = None
        for i, f in enumerate(self.files):  # the first readable image gives the nominal size
            img = self._read(f)
            if img is not None:
                self._first = (i, img)
                self.height, self.width = img.shape[:2]
                break
        if self._first is None:
            raise ValueError(f"none of the {len(self.files)} images in {self.path!r} can be read")

    def __len__(self) -> int:
        return len(self.files)

    def __iter__(self) -> Iterator[Frame]:
        first, img0 = self._first or (-1, None)
        for i, f in enumerate(self.files):
            if i < first:  # already found unreadable (and counted) while looking for the first image
                continue
            img = img0 if i == first else self._read(f)
            img0 = None
            if img is not None:
                yield Frame(img, i / self.fps, self.names[i])

    def _read(self, f: Path) -> np.ndarray | None:
        import cv2

        img = cv2.imread(str(f), cv2.IMREAD_COLOR)
        if img is None:
            why = "no such file" if not f.exists() else "not a readable image"
            log.warning("skipping %s: %s", f, why)
            self.skipped.append({"file": str(f), "why": why})
            return None
        if _truncated(f):
            log.warning("%s is truncated: decoded partially (the missing part is filled in)", f)
            self.partial.append(str(f))
        return np.ascontiguousarray(img)


def _truncated(f: Path) -> bool:
    """True for a JPEG without its end-of-image marker or a PNG without its IEND chunk at the end of the file."""
    with open(f, "rb") as fh:
        head = fh.read(8)
        fh.seek(0, 2)
        fh.seek(max(fh.tell() - 16, 0))
        tail = fh.read().rstrip(b"\x00\r\n ")
    if head.startswith(b"\xff\xd8"):
        return not tail.endswith(b"\xff\xd9")
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return not tail.endswith(b"IEND\xaeB`\x82")
    return False


def _positive_rate(fps: float, what: str) -> float:
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"{what} must be a number of Hz above 0, got {fps}")
    return float(fps)


class VideoSource(Source):
    """A video file, camera or stream through OpenCV. ``capture``: an opened ``cv2.VideoCapture``-like object to
    read instead of opening ``path`` (vpengine.io.live opens cameras and streams; tests use a stand-in camera).

    ``live``: frames come at the source's own rate (a camera, a live stream), so they are read on a thread and the
    newest wins (Note [Live capture]); by default a camera index is live and anything else a file. ``read_timeout``:
    the seconds after which ``capture`` gives up on a frame, when it was opened with one (a stream); a source
    ended by it says so. ``what`` names the source in messages. ``first``: a frame already read from ``capture``
    (to check it delivers) and its stamp: a file yields it first, a live source drops it (stale by the time the frame
    loop starts). A file that ends well before the frame count its header announces (a truncated or damaged file,
    Note [Short videos]) ends with a warning and is listed in ``partial``."""

    def __init__(
        self,
        path: str | Path | int,
        capture: Any = None,
        *,
        live: bool | None = None,
        read_timeout: float | None = None,
        what: str | None = None,
        first: tuple[np.ndarray, float] | None = None,
    ) -> None:
        import cv2

        self.path = path
        self.what = what or (f"camera {path}" if isinstance(path, int) else f"video {str(path)!r}")
        self._cap = capture if capture is not None else cv2.VideoCapture(path if isinstance(path, int) else str(path))
        if not self._cap.isOpened():
            raise ValueError(f"cannot open video {str(path)!r} (missing file or unsupported codec)")
        self.width = int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps = fps if fps and math.isfinite(fps) and fps > 0 else None
        self.live = isinstance(path, int) if live is None else live
        count = self._cap.get(cv2.CAP_PROP_FRAME_COUNT)
        self._n = int(count) if not self.live and math.isfinite(count) and count > 0 else 0
        self.read_timeout = read_timeout
        #: A camera's frames that a newer frame replaced before anyone took them (Note [Live capture]).
        self.missed = 0
        #: This file, when it ended before the frames its header announced (Note [Short videos]).
        self.partial: list[str] = []
        self._first = first
        if first is not None:
            self.height, self.width = first[0].shape[:2]
        self._reader: threading.Thread | None = None
        self._stop = threading.Event()

    def __len__(self) -> int:
        return max(self._n, 0)

    def __iter__(self) -> Iterator[Frame]:
        if self.live:
            yield from self._newest()
            return
        import cv2

        i = 0
        if self._first is not None:
            (img, ts), self._first = self._first, None
            yield Frame(img, ts, f"{i:06d}")
            i += 1
        while True:
            t0 = time.monotonic()
            ok, img = self._cap.read()
            if not ok:
                self._ended(i, time.monotonic() - t0)
                return
            # the frame's position in the video, in seconds
            ts = self._cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
            yield Frame(np.ascontiguousarray(img), ts, f"{i:06d}")
            i += 1

    def _ended(self, frames: int, waited: float) -> None:
        """Say why frames stopped coming, when that is news: a live source ending, a stream's read timing out, or a
        file ending short of the frames its header announced (Note [Short videos])."""
        if self.read_timeout is not None and waited >= 0.9 * self.read_timeout:
            log.warning("%s ended after %d frames: no frame came for %.0f s", self.what, frames, waited)
        elif self.live:
            log.warning("%s ended after %d frames: it stopped delivering", self.what, frames)
        elif frames < self._n - max(SHORT_VIDEO_SLACK, SHORT_VIDEO_SHARE * self._n):
            log.warning(
                "%s ended after %d of the %d frames its header announces: the file may be truncated or damaged "
                "(listed in the summary's inputs_partial)",
                self.what,
                frames,
                self._n,
            )
            self.partial.append(redact(str(self.path)))

    def _newest(self) -> Iterator[Frame]:
        """Note [Live capture]: a camera delivers frames at its own rate whether or not they are read. Read in the
        frame loop, a loop slower than the camera gets ever older frames from the driver's queue (latency grows
        by a frame each time round) until the driver drops some, uncounted. So a thread reads the camera as fast
        as it delivers and keeps only the newest frame, stamped with the time it arrived; the loop takes that one
        (waiting if it has taken it already), and every frame replaced before it was taken is counted in
        ``missed``. Frame names number every frame the camera delivered, so the gaps show in the output too. A
        read that never returns would hang the loop, so a stream is opened with a read timeout (vpengine.io.live):
        a stream that stops ends the source, with a warning."""
        cond = threading.Condition()
        newest: list[Frame | None] = [None]
        ended: list[BaseException | bool] = [False]  # True at the camera's end; the error if reading raised
        stop = self._stop = threading.Event()
        self._first = None  # stale by now: the newest frame is the next one

        def grab() -> None:
            i = 0
            try:
                while not stop.is_set():
                    t0 = time.monotonic()
                    ok, img = self._cap.read()
                    t = time.time()
                    with cond:
                        if not ok:
                            if not stop.is_set():
                                self._ended(i, time.monotonic() - t0)
                            break
                        if newest[0] is not None:
                            self.missed += 1
                        newest[0] = Frame(np.ascontiguousarray(img), t, f"{i:06d}")
                        i += 1
                        cond.notify()
            except BaseException as e:
                with cond:
                    ended[0] = e
            with cond:
                ended[0] = ended[0] or True
                cond.notify()

        reader = self._reader = threading.Thread(target=grab, name="vpengine-camera", daemon=True)
        reader.start()
        try:
            while True:
                with cond:
                    cond.wait_for(lambda: newest[0] is not None or ended[0] is not False)
                    frame, newest[0] = newest[0], None
                    if frame is None:
                        if isinstance(ended[0], BaseException):
                            raise RuntimeError(f"reading {self.what} failed: {ended[0]!r}") from ended[0]
                        return
                yield frame
        finally:
            stop.set()
            reader.join(timeout=1.0)  # a read in progress ends with the camera's next frame

    def close(self) -> None:
        reader = self._reader
        if reader is not None and reader.is_alive():
            self._stop.set()
            # releasing the capture under a read in progress frees what the read is using: let the read end first
            reader.join(timeout=(self.read_timeout or 10.0) + 1.0)
            if reader.is_alive():
                log.warning("%s: a read did not return; leaving its capture open", self.what)
                return
        self._cap.release()


def open_source(spec: str, topic: str | None = None, fps: float | None = None, strict: bool = False) -> Source:
    """A source from a command-line spec: ``synthetic[...]``, an image, a folder of images, a glob of images
    (``frames/*.jpg``), a video file, ``sample:NAME``, a rosbag2 bag (a folder with metadata.yaml, or a .mcap / .db3
    file; ``topic`` names its image topic; ``strict`` stops at its first bad message instead of skipping it, see
    vpengine.io.bag), or a live source (vpengine.io.live): ``camera:N``, a device path (``/dev/video0``), a stream URL
    (``rtsp://...``, ``http://...``) or a GStreamer pipeline (``gst:... ! appsink``). ``fps``: the rate images are
    stamped at (default 30 Hz). ValueError, one line, when the source cannot be read."""
    from vpengine.io import live

    if spec.startswith("synthetic"):
        source: Source = SyntheticSource.parse(spec)
    elif live.is_live(spec):
        o = live.open_live(spec)
        source = VideoSource(
            o.path, o.capture, live=o.live, read_timeout=o.read_timeout, what=o.what, first=(o.image, o.stamp)
        )
    elif spec.startswith("sample:"):
        return open_source(str(sample(spec.split(":", 1)[1])), topic, fps, strict)
    else:
        path = Path(spec)
        if not path.exists() and glob.has_magic(spec):
            files = sorted(Path(f) for f in glob.glob(spec, recursive=True) if Path(f).suffix.lower() in IMAGE_EXTS)
            if not files:
                raise ValueError(f"no images ({', '.join(sorted(IMAGE_EXTS))}) match {spec!r}")
            source = ImageSource(files, spec, fps)
        elif not path.exists():
            raise ValueError(
                f"source {spec!r} does not exist (expected an image, a folder, a glob, a video, a rosbag2 bag, "
                f"camera:N, a device path, a stream URL, gst:PIPELINE, sample:NAME or synthetic)"
            )
        elif (path.is_dir() and (path / "metadata.yaml").is_file()) or (
            path.is_file() and path.suffix.lower() in (".mcap", ".db3")
        ):
            from vpengine.io.bag import BagSource  # rosbags is an optional dependency

            return BagSource(path, topic, strict=strict)
        elif path.is_dir():
            files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_EXTS)
            source = ImageSource(files, path, fps)
        elif path.suffix.lower() in VIDEO_EXTS:
            source = VideoSource(path)
        elif path.suffix.lower() in IMAGE_EXTS:
            source = ImageSource([path], path, fps)
        else:
            raise ValueError(
                f"source {spec!r}: unknown kind (extensions: images {sorted(IMAGE_EXTS)}, video "
                f"{sorted(VIDEO_EXTS)}, bag .mcap/.db3, or a folder)"
            )
    if topic is not None:
        source.close()
        raise ValueError(f"--topic {topic!r} applies to rosbag2 bags only; source {redact(spec)!r} is not a bag")
    return source


def sample_names() -> list[str]:
    """Names of the sample media shipped with the package (``sample:NAME``)."""
    return sorted(p.stem for p in SAMPLES.iterdir() if p.suffix.lower() in IMAGE_EXTS | VIDEO_EXTS)


def sample(name: str) -> Path:
    """The file of a shipped sample (``street``: 5 s of street video; ``cheetah``: a 1080p photo)."""
    for p in SAMPLES.iterdir():
        if p.stem == name and p.suffix.lower() in IMAGE_EXTS | VIDEO_EXTS:
            return p
    raise ValueError(f"no sample named {name!r}; samples: {', '.join(sample_names())}")
