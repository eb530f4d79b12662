"""The heads' pictures live in Foxglove, over ``foxglove-sdk``'s WebSocket server (``pip install 'vpengine[foxglove]'``).

Foxglove opens ``ws://HOST:PORT`` ("Open connection" -> Foxglove WebSocket) and lists, per head::

    /vpengine/<head>/image        foxglove.CompressedImage: the view's picture (depth colours, overlay, boxes)
    /vpengine/<head>/annotations  foxglove.ImageAnnotations (detection heads): a box and a caption per detection,
                                  in the picture's pixels, stamped like the picture

With several cameras each camera a head serves has its own pair, ``/vpengine/<camera>/<head>/...``, whose
``frame_id`` is the camera: one picture per camera and head, never the newest of any camera's.

A pump thread looks at each channel up to ``hz`` times a second and does nothing for channels nobody subscribed to;
pictures come from the same bounded :class:`~vpengine.web.pictures.Pictures` as the page's (Note [Pictures and
frames]). Foxglove's WebSocket protocol has no authentication, so the server binds to loopback only; from another
computer, forward the port (``ssh -L 8765:127.0.0.1:8765 robot``).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from vpengine.visualize import head_kind
from vpengine.web.pictures import FrameLookup, Pictures

if TYPE_CHECKING:
    from vpengine.engine import Engine
    from vpengine.web.pictures import EngineRef
from vpengine.web.server import is_loopback

log = logging.getLogger("vpengine.web")


def _stamp(t: float) -> Any:
    from foxglove.messages import Timestamp

    sec, nsec = divmod(round(t * 1e9), 1_000_000_000)
    return Timestamp(sec=sec, nsec=nsec)


def image_annotations(outputs: dict[str, Any], labels: list[str] | None, scale: float, t: float) -> Any:
    """foxglove.ImageAnnotations of one detection result: a closed box and a 'name score' caption each."""
    from foxglove.messages import (
        Color,
        ImageAnnotations,
        Point2,
        PointsAnnotation,
        PointsAnnotationType,
        TextAnnotation,
    )

    from vpengine.visualize import default_palette

    pal = default_palette(256)
    stamp = _stamp(t)
    points, texts = [], []
    for box, score, label in zip(
        np.asarray(outputs["boxes"], np.float64) * scale, np.asarray(outputs["scores"]), np.asarray(outputs["labels"])
    ):
        x1, y1, x2, y2 = (float(v) for v in box)
        b, g, r = (float(c) / 255 for c in pal[int(label) % 256])
        colour = Color(r=r, g=g, b=b, a=1.0)
        points.append(
            PointsAnnotation(
                timestamp=stamp,
                type=PointsAnnotationType.LineLoop,
                points=[Point2(x=x1, y=y1), Point2(x=x2, y=y1), Point2(x=x2, y=y2), Point2(x=x1, y=y2)],
                outline_color=colour,
                thickness=2.0,
            )
        )
        name = labels[int(label)] if labels and 0 <= int(label) < len(labels) else str(int(label))
        texts.append(
            TextAnnotation(
                timestamp=stamp,
                position=Point2(x=x1, y=max(0.0, y1 - 4)),
                text=f"{name} {float(score):.2f}",
                font_size=12.0,
                text_color=colour,
                background_color=Color(r=0.0, g=0.0, b=0.0, a=0.5),
            )
        )
    return ImageAnnotations(points=points, texts=texts)


class FoxgloveView:
    """Each head's newest picture (and a detection head's boxes) on a Foxglove WebSocket server, until
    :meth:`stop`. ``engine``, ``frames`` and ``frame_color`` as for :class:`~vpengine.web.WebServer`;
    ``pictures`` shares the page's (and its bound) when both run."""

    def __init__(
        self,
        engine: EngineRef,
        host: str = "127.0.0.1",
        port: int = 8765,
        frames: FrameLookup | None = None,
        frame_color: str = "bgr",
        hz: float = 10.0,
        width: int = 640,
        namespace: str = "/vpengine",
        pictures: Pictures | None = None,
    ) -> None:
        try:
            import foxglove
            from foxglove.channels import CompressedImageChannel, ImageAnnotationsChannel
        except ImportError as e:
            raise ImportError(f"the Foxglove view needs foxglove-sdk: pip install 'vpengine[foxglove]' ({e})") from None
        if not is_loopback(host):
            raise ValueError(
                f"Foxglove's WebSocket protocol has no authentication: serve it on 127.0.0.1 (not {host!r}) and "
                "forward the port (ssh -L)"
            )
        if not hz > 0:
            raise ValueError(f"hz must be > 0, got {hz!r}")
        self._get_engine: Callable[[], Engine | None] = engine if callable(engine) else (lambda: engine)
        self.pictures = pictures or Pictures(frames, frame_color)
        self.period, self.width, self.ns = 1.0 / hz, width, namespace.rstrip("/")
        self._context = foxglove.Context()
        self._server = foxglove.start_server(name="vpengine", host=host, port=port, context=self._context)
        self.port = self._server.port
        self._image_channel, self._annotation_channel = CompressedImageChannel, ImageAnnotationsChannel
        # (camera, head) -> its image and annotation channels; camera None with one camera
        self._channels: dict[tuple[str | None, str], tuple[Any, Any | None]] = {}
        self._sent: dict[tuple[str | None, str], int] = {}  # seq of the picture sent last on each
        self.sent = 0  # messages logged
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._pump, name="vpengine-foxglove", daemon=True)
        self._thread.start()
        log.info("Foxglove view at ws://%s:%d", host, self.port)

    @property
    def url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"

    def _heads(self, engine: Engine) -> dict[tuple[str | None, str], tuple[Any, Any | None]]:
        """The channels of every head and camera it serves (made once the engine is there: the ROS 2 core's may
        start late)."""
        if not self._channels:
            several = len(engine.cameras) > 1
            for head in engine.plan.heads:
                kind = head_kind(engine.head_info(head))
                if kind == "generic":
                    continue
                for camera in engine.lanes.served(head) if several else [None]:
                    base = f"{self.ns}/{camera}/{head}" if camera else f"{self.ns}/{head}"
                    image = self._image_channel(f"{base}/image", context=self._context)
                    boxes = (
                        self._annotation_channel(f"{base}/annotations", context=self._context)
                        if kind == "detection"
                        else None
                    )
                    self._channels[(camera, head)] = (image, boxes)
        return self._channels

    def _pump(self) -> None:
        while not self._stop.wait(self.period):
            try:
                self._send_new()
            except Exception as e:  # the engine stopped under us, or a bad result: say so, keep serving
                from vpengine.engine import EngineDeadError

                if not isinstance(e, EngineDeadError):
                    log.warning("Foxglove view: %r", e)

    def _send_new(self) -> None:
        from foxglove.messages import CompressedImage

        engine = self._get_engine()
        if engine is None or not engine.running:
            return
        for (camera, head), (image, boxes) in self._heads(engine).items():
            if not image.has_sinks() and not (boxes is not None and boxes.has_sinks()):
                continue  # nobody subscribed: nothing is drawn or sent
            pic = self.pictures.latest(engine, head, self.width, camera)
            if pic is None or self._sent.get((camera, head)) == pic.seq:
                continue
            self._sent[(camera, head)] = pic.seq
            t_ns = int(pic.capture_time * 1e9)
            frame_id = camera or head
            image.log(
                CompressedImage(timestamp=_stamp(pic.capture_time), frame_id=frame_id, data=pic.jpeg, format="jpeg"),
                log_time=t_ns,
            )
            self.sent += 1
            if boxes is not None and boxes.has_sinks():
                result = engine.latest(head, camera=camera)
                if result is not None and result.seq == pic.seq:  # the boxes of the picture's own result
                    scale = pic.width / result.frame_size[1]  # the picture's frame grid (Note [Pictures and frames])
                    labels = engine.head_info(head).get("labels")
                    outputs = engine.boundary.to_frame(head, dict(result.outputs), result.placement)
                    boxes.log(image_annotations(outputs, labels, scale, pic.capture_time), log_time=t_ns)
                    self.sent += 1

    def stop(self) -> None:
        """Stop the pump and the server. Safe to call twice."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout=5)
        self._server.stop()

    def __enter__(self) -> FoxgloveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
