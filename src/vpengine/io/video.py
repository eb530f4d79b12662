"""Annotated videos that browsers play.

Note [Browser video]
~~~~~~~~~~~~~~~~~~~~
Browsers play H.264 in mp4 (and VP8/VP9 in WebM), not the MPEG-4 Part 2 ('mp4v') that every OpenCV can write.
opencv-python-headless's own FFmpeg has no H.264 encoder, and its VP8/VP9 encoders run at libvpx's slowest
settings, which OpenCV gives no way to change: 180 ms (VP8) and 1.1 s (VP9) per 1536x576 picture on a 2-core CPU,
against 24 ms for mp4v. So an mp4 is written, in this order, by:

1. PyAV (``pip install 'vpengine[video]'``), whose wheels ship FFmpeg with x264: H.264 at the ``veryfast`` preset,
   22 ms per 1536x576 picture and a third of mp4v's size;
2. OpenCV's 'avc1', where OpenCV's FFmpeg has an H.264 encoder (distribution and JetPack builds often do). Where
   it has none, FFmpeg prints why to the terminal, so whether it has one is probed once per process, on a tiny
   file, with the process's stderr borrowed (Note [Borrowing stderr] in io/stderr.py: that window also swallows
   other threads' stderr, so it happens once, not per file);
3. OpenCV's 'mp4v', with a warning that browsers will not play it and how to get H.264.

A ``.webm`` name asks for WebM: VP8 through OpenCV (slow, as said). Any other name's extension picks the container
of the H.264 (or 'mp4v'): only those in :data:`VIDEO_SUFFIXES`, which hold both, are taken. :func:`check_name`
refuses the rest before a run starts: the writer opens at the first annotated frame, and FFmpeg's own refusal of,
say, a ``.gif`` would come then, reading like a missing encoder. H.264 and 4:2:0 colour need an even width and
height: the picture's size is rounded up to even numbers and :func:`fit` letterboxes it by a pixel.
"""

from __future__ import annotations

import logging
import tempfile
import threading
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from vpengine.io.stderr import captured_stderr

log = logging.getLogger("vpengine")

#: What each writer writes, as :attr:`VideoWriter.codec` says it.
H264, VP8, MP4V = "h264", "vp8", "mp4v"
#: The file names a :class:`VideoWriter` writes, by extension (any case): ``.webm`` gets VP8, the others H.264 or
#: 'mp4v' (Note [Browser video]); each was written and read back with PyAV and with OpenCV alone.
VIDEO_SUFFIXES = (".mp4", ".avi", ".m4v", ".mkv", ".mov", ".webm")


def check_name(path: str | Path, what: str = "video") -> Path:
    """``path`` when its extension is one of :data:`VIDEO_SUFFIXES`; else ValueError, one line, naming it and the
    accepted ones. ``what`` names the file in the message (e.g. ``--video``)."""
    p = Path(path)
    if p.suffix.lower() not in VIDEO_SUFFIXES:
        ext = repr(p.suffix) if p.suffix else "no extension"
        raise ValueError(
            f"{what} {str(p)!r}: cannot write a video as {ext}; name it {', '.join(VIDEO_SUFFIXES)} "
            "(browsers play .mp4 and .webm)"
        )
    return p


def even_size(width: int, height: int) -> tuple[int, int]:
    """(width, height) rounded up to even numbers, as H.264's 4:2:0 colour needs."""
    return width + width % 2, height + height % 2


class VideoWriter:
    """Writes BGR uint8 pictures of one ``size`` (width, height; even numbers, :func:`even_size`) to ``path`` at
    ``fps`` with the first encoder that works (Note [Browser video]); :attr:`codec` says which. Raises OSError
    naming the file when nothing can write it, ValueError (:func:`check_name`) when its extension is not a video."""

    def __init__(self, path: str | Path, fps: float, size: tuple[int, int]) -> None:
        self.path = check_name(path)
        self.size = size
        if size != even_size(*size):
            raise ValueError(f"video size must be even numbers of pixels (even_size), got {size[0]}x{size[1]}")
        self._av: Any = None
        self._stream: Any = None
        self._cv: Any = None
        if self.path.suffix.lower() == ".webm":
            self.codec = VP8
            self._cv = _opencv_writer(self.path, "VP80", fps, size)
            if self._cv is None:
                raise OSError(f"cannot write video {str(self.path)!r}: this OpenCV writes no VP8; name an .mp4 instead")
            return
        if self._open_av(fps):
            self.codec = H264
            return
        self.codec = H264
        self._cv = _opencv_writer(self.path, "avc1", fps, size) if _opencv_writes_h264() else None
        if self._cv is None:
            self.codec = MP4V
            self._cv = _opencv_writer(self.path, "mp4v", fps, size)
            if self._cv is None:
                raise OSError(f"cannot write video {str(self.path)!r} (no H.264 encoder, and OpenCV cannot write mp4v)")
            log.warning(
                "%s is MPEG-4 Part 2, which browsers do not play: no H.264 encoder here "
                "(pip install 'vpengine[video]' adds one)",
                self.path,
            )

    def _open_av(self, fps: float) -> bool:
        try:
            import av
        except ImportError:
            return False
        encoder = next((c for c in ("libx264", "libopenh264") if c in av.codecs_available), None)
        if encoder is None:
            return False
        # faststart: the index goes first, so a browser starts playing before it has the whole file
        self._av = av.open(str(self.path), "w", options={"movflags": "faststart"})
        try:
            stream = self._av.add_stream(encoder, rate=Fraction(fps).limit_denominator(1001))
            stream.width, stream.height = self.size
            stream.pix_fmt = "yuv420p"
            if encoder == "libx264":
                stream.options = {"preset": "veryfast", "crf": "23"}
        except Exception:
            self._av.close()
            self._av = None
            raise
        self._stream = stream
        return True

    def write(self, picture: np.ndarray) -> None:
        """One BGR uint8 picture of the writer's size."""
        if picture.shape[:2] != (self.size[1], self.size[0]):
            raise ValueError(f"video picture must be {self.size[0]}x{self.size[1]}, got {picture.shape}")
        if self._av is None:
            self._cv.write(picture)
            return
        import av

        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(picture), format="bgr24")
        self._av.mux(self._stream.encode(frame))

    def close(self) -> None:
        """Flush and close the file (once; later calls do nothing)."""
        if self._av is not None:
            av_file, self._av = self._av, None
            try:
                av_file.mux(self._stream.encode())  # what the encoder still holds
            finally:
                av_file.close()
        if self._cv is not None:
            self._cv.release()
            self._cv = None


def _opencv_writer(path: Path, fourcc: str, fps: float, size: tuple[int, int]) -> Any:
    import cv2

    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, size)
    if w.isOpened():
        return w
    w.release()
    return None


# whether OpenCV's 'avc1' opens here: None until probed (once per process, under the lock)
_avc1: bool | None = None
_avc1_lock = threading.Lock()


def _opencv_writes_h264() -> bool:
    """Whether OpenCV's 'avc1' writer opens here (Note [Browser video]), probed on the first call only."""
    global _avc1
    with _avc1_lock:
        if _avc1 is None:
            with tempfile.TemporaryDirectory(prefix="vpengine-avc1-") as d, captured_stderr() as said:
                probe = _opencv_writer(Path(d) / "probe.mp4", "avc1", 10.0, (64, 64))
                if probe is not None:
                    probe.release()
            for line in said:
                log.debug("opencv avc1: %s", line)
            _avc1 = probe is not None
        return _avc1
