"""rosbag2 bags (sqlite3 and MCAP, any rosbag2 version rosbags reads: Foxy to Jazzy and later) as a frame source, and
as a sink that records every head's outputs with the same message types and header rules as the ROS 2 bridge.

``vpengine run --source BAG --topic /camera/image_raw --out-bag OUT``:

* the source reads ``sensor_msgs/msg/Image`` (rgb8, bgr8, mono8) or ``sensor_msgs/msg/CompressedImage`` (jpeg,
  png) from one topic, in log-time order; each frame's timestamp is its message's ``header.stamp``. A bag is a folder
  with ``metadata.yaml`` or a bare ``.mcap`` / ``.db3`` file. A message that cannot be used (corrupt bytes, an
  unsupported encoding, short data ...) is skipped and listed (``skipped``), and logged in one line naming the bag,
  topic and message index (Note [Rejection log] in :mod:`vpengine.ros2.diagnostics`), so one bad frame does not end a long
  recording; ``strict=True`` stops at the first one instead, with that line as the error.
* the sink writes the input image, ``<ns>/input/compressed`` (sensor_msgs/CompressedImage, JPEG), and every
  head's outputs: ``<ns>/<head>/depth`` (32FC1), ``<ns>/<head>/classes`` (mono8), ``<ns>/<head>/detections``
  (vision_msgs/Detection2DArray 4.x) and, with ``viz``, ``depth_color/compressed`` / ``overlay/compressed``
  (JPEG); every message's header (stamp and frame_id) is its input message's header, and its log time is that
  stamp (Note [Bag contents]). With several cameras (``vpengine run --source BAG --topic front=T1 --topic
  rear=T2``: a camera per topic) each camera's input and outputs are under ``<ns>/<camera>/...``.
  ``distro="humble"`` writes Humble message definitions in a version-8 bag, ``"jazzy"`` Jazzy's in a version-9 bag
  (rosbags writes no older versions).

Note [Bag contents]
~~~~~~~~~~~~~~~~~~~
A recording is of use only with what the heads saw: the input image goes in too, once per frame, so the bag plays
back on its own (``vpengine run -s OUT --topic /vpengine/input/compressed`` reads it as a source) and a viewer lays
the outputs over it. Pictures are JPEG (quality ``JPEG_QUALITY``, image_transport's ``compressed`` topic and
format): as raw bgr8 the two --viz pictures made 55% of a recording (10 frames of sample:street at 768x576: 48.7 MB,
with 1.3 MB a picture a frame); as JPEG the input and both pictures are about 0.2 MB a frame. Outputs that are
data stay exact and as the ROS 2 bridge publishes them: depth as 32FC1 (1.8 MB a 768x576 frame, the bulk of what
is left), class ids as mono8, detections as Detection2DArray.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from vpengine.engine.results import Result
from vpengine.io.base import Frame, Source
from vpengine.io.sinks import JPEG_QUALITY, Sink
from vpengine.ros2.diagnostics import Rejections
from vpengine.ros2.messages import (
    COMPRESSED_TYPE,
    IMAGE_TYPE,
    Header,
    ImageOut,
    InputError,
    compressed_to_frame,
    image_to_frame,
)
from vpengine.ros2.outputs import OutputTopic, normalize_namespace, payload_for, plan_outputs, ros_name

log = logging.getLogger("vpengine.bag")

STORAGES = ("mcap", "sqlite3")
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_TYPE)
_HEADERS_KEPT = 4096
#: Roles whose images are pictures to look at, written as JPEG (Note [Bag contents])
PICTURE_ROLES = ("depth_color", "overlay")
JPEG_FORMAT = "bgr8; jpeg compressed bgr8"  # image_transport's: BGR pixels, JPEG
#: a storage's file suffix inside a bag's folder
_SUFFIXES = {"mcap": ".mcap", "sqlite3": ".db3"}


def check_bag_name(path: str | Path, storage: str = "mcap", what: str = "output bag") -> None:
    """A rosbag2 bag is a folder holding ``metadata.yaml`` and its storage file (``NAME/NAME.mcap``): a path named
    like a storage file (``run.mcap``, ``run.db3``) would make ``run.mcap/run.mcap.mcap``, so it is refused with
    the folder name to give instead and the file that writes."""
    p = Path(path)
    if p.suffix.lower() in _SUFFIXES.values():
        folder = p.with_suffix("")
        raise ValueError(
            f"{what} {str(p)!r}: a rosbag2 bag is a folder that holds its {storage} file; give the folder's name: "
            f"{str(folder)!r} writes {folder / folder.name}{_SUFFIXES.get(storage, '')}"
        )


def _topic_list(conns: list[Any]) -> str:
    seen = sorted({(c.topic, c.msgtype) for c in conns})
    return ", ".join(f"{t} ({m})" for t, m in seen) or "(none)"


class BadMessage(ValueError):
    """A bag message that cannot be used; the text names the bag, topic and message index (0-based) in one line."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(message)
        self.reason = reason


class BagSource(Source):
    """Camera frames from one Image or CompressedImage topic of a rosbag2 bag.

    ``topic`` may be omitted when the bag has exactly one image topic. Frames are in ``color`` order (the engine's
    ``input.color``), each at its own size (``height``/``width`` are the first frame's): the engine's boundary
    scales every frame, so outputs come back at each frame's size (Note [Frame grid] in engine/boundary.py). The exact
    input header of each frame is kept by its frame name (the message index) for the bag sink (:meth:`header_for`).
    Bad messages are skipped and counted in ``bad`` (or, ``strict``, raised as :class:`BadMessage`), see the module
    docstring.
    """

    def __init__(self, path: str | Path, topic: str | None = None, color: str = "bgr", strict: bool = False) -> None:
        from rosbags.rosbag2 import Reader

        from vpengine.ros2.rosbags_msgs import DISTROS, typestore

        self.path = Path(path)
        self.color = color
        self.strict = strict
        try:
            self._reader = Reader(self.path)
            self._reader.open()
        except Exception as e:  # rosbags raises its own error types; name the bag either way
            raise ValueError(f"cannot open bag {str(self.path)!r}: {e}") from None
        try:
            conns = list(self._reader.connections)
            images = sorted({c.topic for c in conns if c.msgtype in IMAGE_TYPES})
            if topic is None:
                if len(images) != 1:
                    raise ValueError(
                        f"bag {str(self.path)!r}: give the image topic (--topic); image topics: "
                        f"{', '.join(images) or '(none)'}; all topics: {_topic_list(conns)}"
                    )
                topic = images[0]
            self.topic = topic
            self._conns = [c for c in conns if c.topic == topic]
            if not self._conns:
                raise ValueError(f"bag {str(self.path)!r} has no topic {topic!r}; topics: {_topic_list(conns)}")
            types = {c.msgtype for c in self._conns}
            if len(types) != 1 or not types <= set(IMAGE_TYPES):
                raise ValueError(
                    f"bag {str(self.path)!r}: topic {topic!r} carries {', '.join(sorted(types))}; accepted: "
                    f"{', '.join(IMAGE_TYPES)}"
                )
            self.msgtype = types.pop()
            distro = (self._reader.ros_distro or "").lower()
            self._ts = typestore(distro if distro in DISTROS else "jazzy")
            self._n = sum(c.msgcount for c in self._conns)
            if self._n == 0:
                raise ValueError(f"bag {str(self.path)!r}: topic {topic!r} has no messages")
            self.rejected = Rejections("bag message skipped", log)
            self.height, self.width = self._first_size()
        except BaseException:
            self._reader.close()
            raise
        #: the messages skipped as bad, as every source lists what it skipped (``vpengine run`` puts the list in
        #: summary.json): bag, topic, message index and why; logged per Note [Rejection log]
        self.skipped: list[dict[str, Any]] = []
        self._headers: collections.OrderedDict[str, Header] = collections.OrderedDict()

    def _first_size(self) -> tuple[int, int]:
        """The size of the first usable frame. Bad messages before it are counted and logged when iteration
        reaches them (or raised here, strict)."""
        reasons: collections.Counter[str] = collections.Counter()
        first = ""
        messages = self._messages()
        try:
            for i, raw in enumerate(messages):
                try:
                    h, w = self._decode(raw, i)[1].shape[:2]
                    return h, w
                except BadMessage as e:
                    if self.strict:
                        raise
                    reasons[e.reason] += 1
                    first = first or str(e)
        finally:
            messages.close()  # release the storage cursor; iteration starts afresh
        raise ValueError(
            f"bag {str(self.path)!r}: none of the {self._n} messages on {self.topic!r} is usable "
            f"({', '.join(f'{n} {r}' for r, n in sorted(reasons.items()))}); the first: {first}"
        )

    def _messages(self) -> Iterator[bytes]:
        i = -1
        try:
            for i, (_conn, _t, raw) in enumerate(self._reader.messages(connections=self._conns)):  # noqa: B007
                yield raw
        except Exception as e:  # the storage itself (a truncated file, a bad chunk): no way past it
            raise ValueError(
                f"bag {str(self.path)!r}: reading {self.topic!r} failed after message {i}: "
                f"{type(e).__name__}: {_line(e)}"
            ) from None

    def _decode(self, raw: bytes, index: int) -> tuple[Header, np.ndarray]:
        where = f"bag {str(self.path)!r}, topic {self.topic!r}, message {index}"
        try:
            msg = self._ts.deserialize_cdr(raw, self.msgtype)
        except Exception as e:  # rosbags' SerdeError, or struct/index/unicode errors on garbage bytes
            raise BadMessage(
                f"{where}: not a valid {self.msgtype} ({len(raw)} bytes): {type(e).__name__}: {_line(e)}",
                "malformed",
            ) from None
        try:
            decode = image_to_frame if self.msgtype == IMAGE_TYPE else compressed_to_frame
            return Header.of(msg.header), decode(msg, self.color)
        except InputError as e:
            raise BadMessage(f"{where}: {e}", e.reason) from None
        except (ValueError, AttributeError, TypeError) as e:
            raise BadMessage(f"{where}: {type(e).__name__}: {_line(e)}", "malformed") from None

    def _bad(self, e: BadMessage, index: int) -> None:
        if self.strict:
            raise e
        self.rejected.add(e.reason, f"{e} (skipped; --strict stops here instead)")
        self.skipped.append({"bag": str(self.path), "topic": self.topic, "message": index, "why": str(e)})

    def __len__(self) -> int:
        return self._n

    def __iter__(self) -> Iterator[Frame]:
        for i, raw in enumerate(self._messages()):
            try:
                header, img = self._decode(raw, i)
            except BadMessage as e:
                self._bad(e, i)
                continue
            name = f"{i:06d}"
            self._headers[name] = header
            if len(self._headers) > _HEADERS_KEPT:
                self._headers.popitem(last=False)
            yield Frame(img, header.seconds, name)

    def header_for(self, result: Result, name: str) -> Header:
        """The exact input header of the frame named ``name`` (see Note [Output headers] in vpengine.ros2.core)."""
        h = self._headers.get(name)
        return h if h is not None else Header.from_seconds(result.capture_time)

    def close(self) -> None:
        self._reader.close()
        if self.skipped:
            indices = [str(s["message"]) for s in self.skipped]
            shown = ", ".join(indices[:20]) + (", ..." if len(indices) > 20 else "")
            log.warning(
                "bag %s, topic %s: %d bad messages skipped (message %s)",
                self.path,
                self.topic,
                len(indices),
                shown,
            )


def _line(e: BaseException) -> str:
    """An exception's text on one line (some libraries' messages span several)."""
    return " ".join(str(e).split()) or "(no message)"


def default_qos() -> list[Any]:
    """ROS 2's default publisher QoS (reliable, volatile, keep last 10), as the offered profile of each topic."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(0, 0)  # 0 = unspecified (the rmw default: infinite)
    return [
        Qos(
            QosHistory.KEEP_LAST,
            10,
            QosReliability.RELIABLE,
            QosDurability.VOLATILE,
            zero,
            zero,
            QosLiveliness.AUTOMATIC,
            zero,
            False,
        )
    ]


def input_topic(namespace: str = "/vpengine", camera: str | None = None) -> str:
    """The topic of the input images in a recorded bag: ``<ns>/input/compressed`` (``<ns>/<camera>/...`` for one of
    several cameras)."""
    base = normalize_namespace(namespace) + ("" if camera is None else f"/{ros_name(camera)}")
    return f"{base}/input/compressed"


class BagSink(Sink):
    """The input images and every head's outputs into a new rosbag2 bag (see the module docstring for topics and
    header rules; Note [Bag contents]). Frames given to :meth:`write` are BGR, as every source of ``vpengine run``
    gives them. ``cameras`` (several cameras: camera -> the heads that serve it) puts each camera's input and
    outputs under its own namespace, ``<ns>/<camera>/...``.

    ``header_for(result, frame_name)`` gives each output's header; by default the result's capture time (from the
    source's timestamps) and ``frame_id``. With a :class:`BagSource`, pass its ``header_for`` to keep the input
    headers exactly.
    """

    def __init__(
        self,
        path: str | Path,
        heads: dict[str, dict[str, Any]],
        *,
        storage: str = "mcap",
        distro: str = "jazzy",
        namespace: str = "/vpengine",
        depth_color: bool = False,
        seg_overlay: bool = False,
        header_for: Callable[[Result, str], Header] | None = None,
        frame_id: str = "camera",
        cameras: Mapping[str, Sequence[str]] | None = None,
    ) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer

        from vpengine.ros2.rosbags_msgs import DISTROS, typestore

        if storage not in STORAGES:
            raise ValueError(f"bag storage {storage!r} is not supported; accepted: {', '.join(STORAGES)}")
        if distro not in DISTROS:
            raise ValueError(f"ROS 2 distribution {distro!r} is not supported; accepted: {', '.join(DISTROS)}")
        check_bag_name(path, storage)
        self.path = Path(path)
        if self.path.exists():
            raise ValueError(f"output bag {str(self.path)!r} exists already; bags are never overwritten")
        self.heads = heads
        self.ts = typestore(distro)
        planned, unmapped = plan_outputs(heads, namespace, depth_color, seg_overlay, cameras)
        self.topics = [
            dataclasses.replace(t, topic=f"{t.topic}/compressed", msgtype=COMPRESSED_TYPE)
            if t.role in PICTURE_ROLES
            else t
            for t in planned
        ]
        self.inputs = {c: input_topic(namespace, c) for c in ([None] if cameras is None else list(cameras))}
        for h in unmapped:
            log.warning("head %r has no ROS 2 message mapping (kind 'generic'); not written to the bag", h)
        self._per_camera = cameras is not None
        self._by_head: dict[tuple[str | None, str], list[OutputTopic]] = collections.defaultdict(list)
        for t in self.topics:
            self._by_head[(t.camera, t.head)].append(t)
        self._header_for = header_for or (
            lambda r, _n: Header.from_seconds(r.capture_time, r.camera if self._per_camera else frame_id)
        )
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self._writer = Writer(self.path, version=DISTROS[distro][1], storage_plugin=plugin)  # type: ignore[arg-type]
        self._writer.open()
        try:
            self._conns = {
                t.topic: self._writer.add_connection(
                    t.topic, t.msgtype, typestore=self.ts, offered_qos_profiles=default_qos()
                )
                for t in self.topics
            }
            for topic in self.inputs.values():
                self._conns[topic] = self._writer.add_connection(
                    topic, COMPRESSED_TYPE, typestore=self.ts, offered_qos_profiles=default_qos()
                )
        except BaseException:
            self._writer.close()
            raise
        self.written: collections.Counter[str] = collections.Counter()
        self.skipped: collections.Counter[str] = collections.Counter()
        # (camera, frame id) of the input images written: each once, with whichever head answers its frame first
        self._inputs_written: collections.OrderedDict[tuple[str, int], None] = collections.OrderedDict()

    def write(self, result: Result, frame: np.ndarray | None, name: str) -> None:
        camera = result.camera if self._per_camera else None
        topics = self._by_head.get((camera, result.head))
        if not topics:
            return
        header = self._header_for(result, name)
        self._write_input(result, camera, frame, header)
        info = self.heads[result.head]
        for t in topics:
            payload = payload_for(t, result.outputs, info, header, frame)
            if payload is None:  # an overlay whose input frame the pipeline no longer holds
                self.skipped[t.topic] += 1
                continue
            if t.msgtype == COMPRESSED_TYPE:
                self._write_jpeg(t.topic, header, _pixels(payload))
                continue
            from vpengine.ros2.rosbags_msgs import to_rosbags

            raw = self.ts.serialize_cdr(to_rosbags(self.ts, payload), t.msgtype)
            self._writer.write(self._conns[t.topic], header.ns, raw)
            self.written[t.topic] += 1

    def _write_input(self, result: Result, camera: str | None, frame: np.ndarray | None, header: Header) -> None:
        key = (result.camera, result.frame_id)
        if key in self._inputs_written:
            return
        self._inputs_written[key] = None
        if len(self._inputs_written) > _HEADERS_KEPT:
            self._inputs_written.popitem(last=False)
        topic = self.inputs[camera]
        if frame is None:
            self.skipped[topic] += 1
        else:
            self._write_jpeg(topic, header, frame)

    def _write_jpeg(self, topic: str, header: Header, bgr: np.ndarray) -> None:
        import cv2

        from vpengine.ros2.rosbags_msgs import compressed_msg

        ok, data = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:
            raise OSError(f"cannot encode a {bgr.shape} picture as JPEG for {topic}")
        raw = self.ts.serialize_cdr(compressed_msg(self.ts, header, JPEG_FORMAT, data.reshape(-1)), COMPRESSED_TYPE)
        self._writer.write(self._conns[topic], header.ns, raw)
        self.written[topic] += 1

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None  # type: ignore[assignment]
        if sum(self.skipped.values()):
            log.warning("bag %s: images skipped (input frame gone): %s", self.path, dict(self.skipped))


def _pixels(img: ImageOut) -> np.ndarray:
    """A bgr8 :class:`ImageOut`'s pixels as HxWx3 (a view)."""
    return img.data.reshape(img.height, img.width, 3)
