"""Each head's newest result as a JPEG: made only when asked, at most one at a time, at most ``max_hz`` per head.

Note [Pictures and frames]
~~~~~~~~~~~~~~~~~~~~~~~~~~
Segmentation overlays and detection boxes are drawn on the input frame, which the engine does not keep. Whoever
feeds the engine (a pipeline, the ROS 2 core) keeps recent frames by frame id in one store,
:class:`vpengine.recent_frames.RecentFrames`, and lends its lookup: ``frames.frame(frame_id) -> image or None``.
A picture is drawn on the frame *of the result's own frame id* or on nothing (a dark canvas of the frame's size):
never on the newest frame, which would pair a result with a frame it was not computed from. ``Picture.on_frame`` says which it was.

The picture is drawn in the result's frame's own grid (``Result.frame_size``, Note [Frame grid] in engine/boundary.py),
never in the config's input size: a frame of another size than the input gets its overlays at its own size, and a
head that keeps the native grid (``Result.grid == "native"``) has its outputs mapped to the frame first, through
the boundary's door out (``Boundary.to_frame``), as the engine maps every other head's. A kept frame of another
size than the result's is not its frame.

Cost: nothing runs until a picture is requested. A request takes the head's newest result borrowed (no copy of
its outputs, Note [Borrowed results] in ``engine/results.py``), draws at the requested width (shrinking first, so a 1080p
overlay costs what a 640-pixel one does) and encodes. One lock serialises the drawing, so any number of viewers use
at most one core; a picture younger than ``1 / max_hz`` is served again as it is, so they draw each head at most
``max_hz`` times a second whatever they ask for.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from vpengine import visualize
from vpengine.visualize import head_kind

if TYPE_CHECKING:
    from vpengine.engine import Engine

    #: The engine a view shows: an Engine, or a callable returning it or None (one that starts later, as the ROS 2
    #: core's may)
    EngineRef = Engine | Callable[[], Engine | None]

#: frame id -> the input frame it names (HxWx3 uint8), or None once it is forgotten
FrameLookup = Callable[[int], "np.ndarray | None"]

DEFAULT_WIDTH = 640
JPEG_QUALITY = 80


@dataclass(frozen=True)
class Picture:
    jpeg: bytes
    head: str
    seq: int  # the result's sequence number in its head's output mailbox
    frame_id: int
    capture_time: float
    latency: float
    #: True: drawn on the result's own input frame; False: the outputs alone (the frame was not there)
    on_frame: bool
    width: int  # of the picture, in pixels
    asked: int  # the width asked for (the picture is narrower when the frame is)
    made_at: float  # time.monotonic()
    camera: str | None = None  # the camera asked for (None: the newest of any camera's)


def _host(value: Any) -> Any:
    """A result output as a host array (device outputs are torch tensors)."""
    if hasattr(value, "detach"):
        t = value.detach()
        return (t.float() if t.dtype.is_floating_point else t).cpu().numpy()
    return value


def _shrink(image: np.ndarray, width: int, nearest: bool = False) -> np.ndarray:
    """``image`` at most ``width`` wide, aspect kept: area-averaged, or ``nearest`` (class ids of any dtype)."""
    import cv2

    h, w = image.shape[:2]
    if w <= width:
        return image
    height = max(1, round(h * width / w))
    if nearest:
        return image[(np.arange(height) * h) // height][:, (np.arange(width) * w) // width]
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


def render(
    info: dict[str, Any], outputs: dict[str, Any], frame: np.ndarray | None, width: int = DEFAULT_WIDTH
) -> np.ndarray | None:
    """A BGR picture of one result at most ``width`` pixels wide: depth colour-mapped, segmentation over the frame,
    boxes on the frame; without a frame, the classes' colours alone and boxes on a dark canvas. None for heads
    without a picture (``generic``). ``frame`` (BGR) must be the result's own input frame (Note [Pictures and
    frames])."""
    kind = head_kind(info)
    if kind == "depth":
        if "depth_color" in outputs:  # the head colour-mapped it on the device already
            return _shrink(np.asarray(outputs["depth_color"]), width)
        if "depth" not in outputs:
            return None
        return visualize.colorize_depth(_shrink(np.asarray(outputs["depth"], np.float32), width))
    if kind == "segmentation":
        classes = _shrink(np.asarray(outputs["classes"]), width, nearest=True)
        base = np.zeros((*classes.shape, 3), np.uint8) if frame is None else _shrink(frame, width)
        pal = info.get("palette")
        palette = None if pal is None else np.asarray(pal, np.uint8)
        return visualize.overlay_segmentation(base, classes, palette, alpha=1.0 if frame is None else 0.5)
    if kind == "detection":
        if frame is None:
            h, w = info["frame_size"]
            canvas = np.full((h, w, 3), 24, np.uint8)
        else:
            canvas = frame
        small = _shrink(canvas, width)
        scale = small.shape[1] / canvas.shape[1]
        boxes = np.asarray(outputs["boxes"], np.float32) * scale
        return visualize.draw_detections(  # draws on a copy
            small,
            boxes,
            np.asarray(outputs["scores"]),
            np.asarray(outputs["labels"]),
            info.get("labels"),
        )
    return None


class Pictures:
    """JPEGs of heads' newest results for a running engine (Note [Pictures and frames])."""

    def __init__(self, frames: FrameLookup | None = None, frame_color: str = "bgr", max_hz: float = 10.0) -> None:
        if frame_color not in ("bgr", "rgb"):
            raise ValueError(f"frame_color must be 'bgr' or 'rgb', got {frame_color!r}")
        if not max_hz > 0:
            raise ValueError(f"max_hz must be > 0, got {max_hz!r}")
        self.frames = frames
        self.frame_color = frame_color
        self.min_interval = 1.0 / max_hz
        self._lock = threading.Lock()
        # (camera, head) -> its newest picture (at the width asked for last); camera None: of any camera
        self._cache: dict[tuple[str | None, str], Picture] = {}
        self._infos: dict[str, dict[str, Any]] = {}
        self.made = 0  # pictures drawn and encoded (not served from the cache)

    def _info(self, engine: Engine, head: str) -> dict[str, Any]:
        info = self._infos.get(head)
        if info is None:
            info = self._infos[head] = engine.head_info(head)
        return info

    def _frame(self, frame_id: int) -> np.ndarray | None:
        if self.frames is None:
            return None
        frame = self.frames(frame_id)
        if frame is None:
            return None
        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
            return None
        return frame[..., ::-1] if self.frame_color == "rgb" else frame

    def latest(
        self, engine: Engine, head: str, width: int = DEFAULT_WIDTH, camera: str | None = None
    ) -> Picture | None:
        """The newest picture of ``head`` at most ``width`` pixels wide (KeyError for an unknown head), or None while
        it has no result (or no picture: a ``generic`` head). ``camera``: of that camera's frames (ValueError for one
        the head does not serve); None: the newest of any camera's. A picture younger than ``1 / max_hz`` comes
        back as it is, whatever its width."""
        import cv2

        key = (camera, head)
        with self._lock:
            cached = self._cache.get(key)
            now = time.monotonic()
            if cached is not None and now - cached.made_at < self.min_interval:
                return cached
            info = self._info(engine, head)
            # borrowed: nothing copied (Note [Borrowed results])
            result = engine.latest(head, copy=False, camera=camera)
            if result is None:
                return None
            if cached is not None and cached.seq == result.seq and cached.asked == width:
                return cached
            size = tuple(result.frame_size)
            frame = self._frame(result.frame_id)
            if frame is not None and frame.shape[:2] != size:
                frame = None  # not the frame these outputs were computed from
            outputs = engine.boundary.to_frame(head, {k: _host(v) for k, v in result.outputs.items()}, result.placement)
            image = render({**info, "frame_size": size}, outputs, frame, width)
            if image is None:
                return None
            ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            if not ok:
                raise RuntimeError(f"JPEG encoding of {head!r}'s picture failed")
            pic = Picture(
                buf.tobytes(),
                head,
                result.seq,
                result.frame_id,
                result.capture_time,
                result.latency,
                frame is not None,
                image.shape[1],
                width,
                time.monotonic(),
                camera,
            )
            del result  # the borrowed slot goes back to the engine
            self._cache[key] = pic
            self.made += 1
            return pic
