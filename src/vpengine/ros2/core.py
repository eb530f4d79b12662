"""The transport-agnostic core of the ROS 2 interfaces: what goes on the wire, decided once.

The DDS bridge (:mod:`vpengine.ros2.bridge`), the rclpy node (:mod:`vpengine.ros2.node`) and the rosbag2 source and
sink (:mod:`vpengine.io.bag`) all call this module; none of it imports a middleware. Messages are read duck-typed
(``msg.height``, ``msg.encoding``, ``msg.data``, ``msg.header.stamp.sec`` ...), so a cyclonedds IDL object, an rclpy
message, a rosbags message or :class:`vpengine.ros2.cdr.ImageView` all work. Outputs are produced as small neutral
objects (:class:`ImageOut`, :class:`DetectionsOut`, :class:`DiagnosticsOut`) that each transport turns into its own
message objects or bytes.

Note [Output headers]: every output of a head carries the ``header`` (stamp *and* frame_id) of the input message it
was computed from, never the time of publishing. The engine only knows integer frame ids and a float capture time;
a float cannot hold a ROS stamp exactly (1.7e9 s has a resolution of ~240 ns), so :class:`FrameBook` keeps the exact
input header per engine frame id, and outputs look their header up by the result's frame id. Only if the book has
already forgotten that frame (more than ``FrameBook.headers`` frames in flight, which the engine never has) does the
header fall back to the float capture time, which is still the input's time; that is counted
(``header_fallbacks``).
"""

from __future__ import annotations

import collections
import json
import logging
import math
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from vpengine.visualize import head_kind

log = logging.getLogger("vpengine.ros2")

# Input frames are zero-copy, read-only views of received message bytes; Engine.submit only copies *from* them, so
# PyTorch's warning about wrapping a non-writable array (torch.from_numpy) does not apply. Filter exactly that one.
warnings.filterwarnings("ignore", message="The given NumPy array is not writable", category=UserWarning)

#: sensor_msgs/Image encodings accepted as input, with their channel counts.
INPUT_ENCODINGS: dict[str, int] = {"rgb8": 3, "bgr8": 3, "mono8": 1}
#: sensor_msgs/CompressedImage codecs accepted as input (decoded by OpenCV).
COMPRESSED_CODECS = ("jpeg", "png")

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
DETECTIONS_TYPE = "vision_msgs/msg/Detection2DArray"
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
KEYVALUE_TYPE = "diagnostic_msgs/msg/KeyValue"
STRING_TYPE = "std_msgs/msg/String"

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR, STALE = 0, 1, 2, 3

#: QoS profiles of the output topics (Note [Output QoS]); the first is the default.
OUTPUT_QOS = ("latest", "default")

# Note [Output QoS]: outputs must stay fresh when a subscriber or the machine cannot keep up. Measured with 1080p
# frames at 30 Hz, a subscriber that copies each image and a busy CPU (benchmarks/results/
# ros2_bridge_throughput.json), two queues made outputs seconds old: (1) a reliable keep-last-10 writer keeps up to
# ten unacknowledged 8 MB images per topic and a write blocks while a slow reader catches up, so (2) results waited
# for the output thread in the engine's result stream and went out in order, each older than the last. So: outputs
# are reliable (a best-effort writer matches no reliable subscriber, ROS 2's default) but keep last 1 ("latest"),
# so a writer holds one image and never more; and with newest-wins input (input_mode: latest) the output thread
# publishes only each head's newest result (poll_outputs), counting the ones it skips. ROS 2's default profile
# stays available ("default", for recording every output).

#: Rate values (case-insensitive) that mean "no limit", in rate commands.
UNLIMITED_WORDS = ("max", "none", "null", "unlimited", "inf", "-1")


class InputError(ValueError):
    """An input message the engine cannot use; the message names what was wrong and what is accepted.

    ``reason`` is a short key for what kind of wrong it is (``encoding``, ``empty``, ``step``, ``short_data``,
    ``format``, ``undecodable``, ``malformed`` ...): rejections are counted and logged per reason (:class:`Rejections`).
    """

    def __init__(self, message: str, reason: str = "invalid") -> None:
        super().__init__(message)
        self.reason = reason


# ------------------------------------------------------------------------------------------------- headers
@dataclass(frozen=True)
class Header:
    """A std_msgs/Header: stamp (builtin_interfaces/Time) and frame_id, kept exactly (integers, not a float)."""

    sec: int
    nanosec: int
    frame_id: str = ""

    @classmethod
    def of(cls, header: Any) -> Header:
        """From any ROS header object (``header.stamp.sec``, ``header.stamp.nanosec``, ``header.frame_id``)."""
        if isinstance(header, Header):
            return header
        return cls(int(header.stamp.sec), int(header.stamp.nanosec), str(header.frame_id))

    @classmethod
    def from_seconds(cls, t: float, frame_id: str = "") -> Header:
        ns = round(float(t) * 1e9)
        return cls(ns // 1_000_000_000, ns % 1_000_000_000, frame_id)

    @classmethod
    def from_ns(cls, ns: int, frame_id: str = "") -> Header:
        return cls(int(ns) // 1_000_000_000, int(ns) % 1_000_000_000, frame_id)

    @property
    def seconds(self) -> float:
        return self.sec + self.nanosec * 1e-9

    @property
    def ns(self) -> int:
        return self.sec * 1_000_000_000 + self.nanosec


class FrameBook:
    """Engine frame id -> the input's exact :class:`Header` (and the input frame, for overlays). Bounded, thread-safe.

    See Note [Output headers]. ``frames`` > 0 keeps that many recent input frames (segmentation overlays need the
    picture the classes were computed from); 0 keeps none.
    """

    def __init__(self, headers: int = 4096, frames: int = 0) -> None:
        if headers < 1 or frames < 0:
            raise ValueError(f"FrameBook needs headers >= 1 and frames >= 0, got {headers} and {frames}")
        self._headers: collections.OrderedDict[int, Header] = collections.OrderedDict()
        self._frames: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self._n_headers, self._n_frames = headers, frames
        self._lock = threading.Lock()

    @property
    def keeps_frames(self) -> bool:
        return self._n_frames > 0

    def add(self, frame_id: int, header: Header, frame: np.ndarray | None = None) -> None:
        with self._lock:
            self._headers[frame_id] = header
            if len(self._headers) > self._n_headers:
                self._headers.popitem(last=False)
            if self._n_frames and frame is not None:
                self._frames[frame_id] = frame
                if len(self._frames) > self._n_frames:
                    self._frames.popitem(last=False)

    def header(self, frame_id: int) -> Header | None:
        with self._lock:
            return self._headers.get(frame_id)

    def frame(self, frame_id: int) -> np.ndarray | None:
        with self._lock:
            return self._frames.get(frame_id)


# ------------------------------------------------------------------------------------------------ decoding
def as_uint8(data: Any) -> np.ndarray:
    """A flat uint8 view of message data (bytes, bytearray, memoryview, array.array, numpy), copying only lists."""
    if isinstance(data, np.ndarray):
        return np.ascontiguousarray(data).reshape(-1).view(np.uint8)
    if isinstance(data, (list, tuple)):  # cyclonedds' own deserializer gives lists; small test messages only
        return np.asarray(data, dtype=np.uint8)
    return np.frombuffer(data, dtype=np.uint8)


def image_to_frame(msg: Any, color: str = "bgr") -> np.ndarray:
    """A sensor_msgs/Image as an HxWx3 uint8 frame in ``color`` order ("bgr" or "rgb").

    Accepts rgb8, bgr8 and mono8 (grey is replicated to three channels). Rows may be padded (``step`` larger than
    width x channels). ``is_bigendian`` only orders the bytes of multi-byte pixels; every accepted encoding has one
    byte per channel, so both values decode the same. The result is a view of the message data when no conversion
    is needed (bgr8 in, bgr wanted, unpadded rows), else one copy. Channel swaps and grey-to-colour go through
    ``cv2.cvtColor`` (vectorised, threaded): at 1080p it takes about 0.2 ms where the numpy ``[..., ::-1]`` copy it
    replaced took 7 ms on the input thread (``decode_ms`` in benchmarks/results/ros2_bridge_throughput.json).
    """
    import cv2

    encoding = str(msg.encoding)
    channels = INPUT_ENCODINGS.get(encoding)
    if channels is None:
        raise InputError(
            f"sensor_msgs/Image encoding {encoding!r} is not supported; accepted: {', '.join(INPUT_ENCODINGS)}",
            "encoding",
        )
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h <= 0 or w <= 0:
        raise InputError(f"sensor_msgs/Image is empty ({w}x{h}, encoding {encoding})", "empty")
    row = w * channels
    if step < row:
        raise InputError(
            f"sensor_msgs/Image step {step} is smaller than width x channels = {w} x {channels} = {row} ({encoding})",
            "step",
        )
    data = as_uint8(msg.data)
    if data.size < step * (h - 1) + row:
        raise InputError(
            f"sensor_msgs/Image data holds {data.size} bytes; a {w}x{h} {encoding} image with step {step} "
            f"needs {step * h}",
            "short_data",
        )
    if step == row:
        img = data[: h * row].reshape(h, w, channels)
    else:  # padded rows: a strided view, no copy yet (OpenCV reads it as a matrix with a row step)
        img = np.lib.stride_tricks.as_strided(data, shape=(h, w, channels), strides=(step, channels, 1))
    if channels == 1:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)  # three equal channels: the same in either order
    if encoding[:3] != color:
        return cv2.cvtColor(img, cv2.COLOR_RGB2BGR)  # the same swap either way
    return np.ascontiguousarray(img)


def compressed_codec(fmt: str, data: np.ndarray) -> str:
    """The codec of a CompressedImage from its ``format`` (``jpeg``, ``png``, or image_transport's
    ``"bgr8; jpeg compressed bgr8"``), or from the data's magic bytes when ``format`` is empty."""
    f = fmt.lower()
    if "compresseddepth" in f:
        raise InputError(
            f"sensor_msgs/CompressedImage format {fmt!r} (depth) is not a camera image; accepted: "
            f"{', '.join(COMPRESSED_CODECS)}",
            "format",
        )
    if "jpeg" in f or "jpg" in f:
        return "jpeg"
    if "png" in f:
        return "png"
    if not f.strip():
        head = bytes(data[:8])
        if head[:3] == b"\xff\xd8\xff":
            return "jpeg"
        if head == b"\x89PNG\r\n\x1a\n":
            return "png"
    raise InputError(
        f"sensor_msgs/CompressedImage format {fmt!r} is not supported; accepted: "
        f"{', '.join(COMPRESSED_CODECS)} (e.g. 'jpeg', 'png', 'bgr8; jpeg compressed bgr8')",
        "format",
    )


def compressed_to_frame(msg: Any, color: str = "bgr") -> np.ndarray:
    """A sensor_msgs/CompressedImage (jpeg or png) as an HxWx3 uint8 frame in ``color`` order.

    image_transport always compresses colour images in BGR order (``"rgb8; jpeg compressed bgr8"`` says so), and
    OpenCV decodes to BGR, so the decoded pixels are BGR whatever the original encoding was.
    """
    import cv2

    data = as_uint8(msg.data)
    codec = compressed_codec(str(msg.format), data)
    if data.size == 0:
        raise InputError(f"sensor_msgs/CompressedImage ({codec}) has no data", "empty")
    img = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(
            f"sensor_msgs/CompressedImage: {data.size} bytes of {codec} data could not be decoded",
            "undecodable",
        )
    if color == "rgb":
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img


# -------------------------------------------------------------------------------------------------- output
@dataclass(frozen=True)
class OutputTopic:
    """One published stream: a head's output in one role, on one ROS topic, with one message type."""

    head: str
    #: depth | depth_color | classes | overlay | detections
    role: str
    topic: str
    msgtype: str
    #: the camera whose outputs it carries, with several cameras (None: the one camera)
    camera: str | None = None


@dataclass
class ImageOut:
    """A sensor_msgs/Image to publish; ``data`` is a flat uint8 view of the pixels (no copy)."""

    header: Header
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int
    data: np.ndarray


@dataclass
class Detection:
    """One vision_msgs/Detection2D: an axis-aligned box (centre, size, pixels) and one class hypothesis."""

    center_x: float
    center_y: float
    size_x: float
    size_y: float
    class_id: str
    score: float


@dataclass
class DetectionsOut:
    """A vision_msgs/Detection2DArray to publish."""

    header: Header
    detections: list[Detection]


@dataclass
class Status:
    """One diagnostic_msgs/DiagnosticStatus."""

    level: int
    name: str
    message: str
    hardware_id: str
    values: list[tuple[str, str]] = field(default_factory=list)


@dataclass
class DiagnosticsOut:
    """A diagnostic_msgs/DiagnosticArray to publish."""

    header: Header
    status: list[Status]


Payload = ImageOut | DetectionsOut


def ros_name(text: str) -> str:
    """A ROS name token from a head name: ROS names allow letters, digits and '_' only ('-' becomes '_')."""
    out = "".join(c if c.isalnum() or c == "_" else "_" for c in text)
    return out if out and not out[0].isdigit() else f"_{out}"


def normalize_namespace(ns: str) -> str:
    """``vpengine`` / ``/vpengine/`` -> ``/vpengine``; ``/`` or empty -> ``""`` (topics at the root)."""
    parts = [p for p in ns.strip().split("/") if p]
    for p in parts:
        if ros_name(p) != p:
            raise ValueError(f"namespace {ns!r}: {p!r} is not a valid ROS name (letters, digits and '_')")
    return "".join(f"/{p}" for p in parts)


def plan_outputs(
    heads: Mapping[str, Mapping[str, Any]],
    namespace: str = "/vpengine",
    depth_color: bool = False,
    seg_overlay: bool = False,
    cameras: Mapping[str, Sequence[str]] | None = None,
) -> tuple[list[OutputTopic], list[str]]:
    """The topics every head publishes on, by its kind; and the heads that have no ROS mapping (kind "generic").

    ``<ns>/<head>/depth`` (32FC1) [+ ``depth_color`` (bgr8)], ``<ns>/<head>/classes`` (mono8) [+ ``overlay``
    (bgr8)], ``<ns>/<head>/detections`` (vision_msgs/Detection2DArray). ``cameras`` (several cameras: camera -> the
    heads that serve it): each camera's outputs under its own namespace instead, ``<ns>/<camera>/<head>/...``.
    """
    ns = normalize_namespace(namespace)
    topics: list[OutputTopic] = []
    unmapped: list[str] = []
    seen: dict[str, str] = {}
    layout = {None: list(heads)} if cameras is None else dict(cameras)
    for camera, served in layout.items():
        for head in served:
            base = f"{ns}/{ros_name(head)}" if camera is None else f"{ns}/{ros_name(camera)}/{ros_name(head)}"
            what = head if camera is None else f"{head}@{camera}"
            if base in seen:
                raise ValueError(f"heads {seen[base]!r} and {what!r} map to the same ROS topic prefix {base!r}")
            seen[base] = what
            kind = head_kind(heads[head])
            if kind == "depth":
                topics.append(OutputTopic(head, "depth", f"{base}/depth", IMAGE_TYPE, camera))
                if depth_color:
                    topics.append(OutputTopic(head, "depth_color", f"{base}/depth_color", IMAGE_TYPE, camera))
            elif kind == "segmentation":
                topics.append(OutputTopic(head, "classes", f"{base}/classes", IMAGE_TYPE, camera))
                if seg_overlay:
                    topics.append(OutputTopic(head, "overlay", f"{base}/overlay", IMAGE_TYPE, camera))
            elif kind == "detection":
                topics.append(OutputTopic(head, "detections", f"{base}/detections", DETECTIONS_TYPE, camera))
            elif head not in unmapped:
                unmapped.append(head)
    return topics, unmapped


def image_out(array: np.ndarray, encoding: str, header: Header) -> ImageOut:
    """Wrap an HxW or HxWxC array as an :class:`ImageOut` (a view when the array is contiguous)."""
    a = np.ascontiguousarray(array)
    if a.ndim not in (2, 3):
        raise ValueError(f"an image must be HxW or HxWxC, got shape {a.shape}")
    h, w = a.shape[:2]
    row = w * (a.shape[2] if a.ndim == 3 else 1) * a.dtype.itemsize
    big = int(a.dtype.byteorder == ">" or (a.dtype.byteorder == "=" and sys.byteorder == "big"))
    return ImageOut(header, h, w, encoding, big if a.dtype.itemsize > 1 else 0, row, a.reshape(-1).view(np.uint8))


def detections_out(outputs: Mapping[str, Any], label_names: Sequence[str] | None, header: Header) -> DetectionsOut:
    """Detections (``boxes`` x1,y1,x2,y2 in input pixels, ``scores``, ``labels``) as a Detection2DArray.

    The class id is the head's label name for that class (the numeric id as text when the head has no names).
    """
    boxes = np.asarray(outputs["boxes"], dtype=np.float64).reshape(-1, 4)
    scores = np.asarray(outputs["scores"], dtype=np.float64).reshape(-1)
    labels = np.asarray(outputs["labels"]).astype(np.int64).reshape(-1)
    n = min(len(boxes), len(scores), len(labels))
    if "count" in outputs:
        n = min(n, int(outputs["count"]))
    dets = []
    for (x1, y1, x2, y2), score, label in zip(boxes[:n].tolist(), scores[:n].tolist(), labels[:n].tolist()):
        name = label_names[label] if label_names is not None and 0 <= label < len(label_names) else str(label)
        dets.append(Detection((x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1, name, score))
    return DetectionsOut(header, dets)


def payload_for(
    topic: OutputTopic,
    outputs: Mapping[str, Any],
    info: Mapping[str, Any],
    header: Header,
    frame_bgr: np.ndarray | None,
) -> Payload | None:
    """The message of one output topic for one result (None: an overlay whose input frame is gone)."""
    from vpengine import visualize

    role = topic.role
    if role == "depth":
        return image_out(np.asarray(outputs["depth"], dtype=np.float32), "32FC1", header)
    if role == "depth_color":
        return image_out(visualize.colorize_depth(np.asarray(outputs["depth"])), "bgr8", header)
    if role == "classes":
        cls = np.asarray(outputs["classes"])
        if cls.dtype == np.uint8:
            return image_out(cls, "mono8", header)
        if cls.size and (cls.min() < 0 or cls.max() > 65535):
            raise ValueError(f"head {topic.head!r}: class ids {cls.min()}..{cls.max()} do not fit mono8/mono16")
        big = cls.size and cls.max() > 255
        return image_out(cls.astype(np.uint16 if big else np.uint8), "mono16" if big else "mono8", header)
    if role == "overlay":
        if frame_bgr is None:
            return None
        pal = info.get("palette")
        picture = visualize.overlay_segmentation(
            frame_bgr, np.asarray(outputs["classes"]), None if pal is None else np.asarray(pal, np.uint8)
        )
        return image_out(picture, "bgr8", header)
    if role == "detections":
        return detections_out(outputs, info.get("labels"), header)
    raise ValueError(f"unknown output role {role!r}")


# --------------------------------------------------------------------------------------------------- input
def input_topics(given: Sequence[str]) -> str | dict[str, str]:
    """Input topics as given (``--input-topic``, the node's ``input_topics``) -> the one camera's topic, or camera
    name -> topic (``NAME=TOPIC`` each, several cameras). ValueError for a mix, a camera named twice or several
    unnamed topics."""
    from vpengine.config import split_camera

    named = [split_camera(str(t)) for t in given]
    if not named:
        raise ValueError("no input topic given")
    if len(named) == 1 and named[0][0] is None:
        return named[0][1]
    if any(n is None for n, _ in named):
        raise ValueError(
            f"input topics {list(given)}: with several, name each one's camera: NAME=TOPIC (e.g. front=/front/image)"
        )
    names = [n for n, _ in named]
    dup = sorted({n for n in names if names.count(n) > 1})  # type: ignore[type-var]
    if dup:
        raise ValueError(f"input topics: each camera once; repeated: {dup}")
    return {n: t for n, t in named if n is not None}


# ------------------------------------------------------------------------------------------------- control
def parse_rate(text: str) -> float | None:
    """A rate from a command: Hz as a number >= 0 (``"5"``, ``"2.5"``; ``"0"`` pauses), or ``max`` / ``none`` /
    ``unlimited`` / ``inf`` / ``-1`` for no limit. Raises ValueError naming the bad value and what is accepted."""
    t = str(text).strip().lower()
    if t in UNLIMITED_WORDS:
        return None
    try:
        hz = float(t)
    except ValueError:
        hz = math.nan
    if not math.isfinite(hz) or hz < 0:
        raise ValueError(
            f"rate {text!r} is not a rate; accepted: a number of Hz >= 0 (0 pauses) or one of "
            f"{', '.join(UNLIMITED_WORDS)} (no limit)"
        )
    return hz


def parse_rate_command(
    key: str, value: str, models: Sequence[str], cameras: Sequence[str] = ()
) -> tuple[str, float | None]:
    """A rate command (diagnostic_msgs/KeyValue ``{key: model, value: rate}``) -> (model, Hz or None). ``key`` may
    be ``model@camera``: that model's rate for one of ``cameras`` alone (:func:`model_at` splits it)."""
    model_at(key, models, cameras)
    return str(key).strip(), parse_rate(value)


def model_at(key: str, models: Sequence[str], cameras: Sequence[str] = ()) -> tuple[str, str | None]:
    """``model`` or ``model@camera`` -> (model, camera or None: all its cameras); ValueError naming the models or
    cameras when either is unknown."""
    model, at, camera = str(key).strip().partition("@")
    if model not in models:
        raise ValueError(f"rate command for unknown model {key!r}; models: {', '.join(models)}")
    if at and camera not in cameras:
        raise ValueError(
            f"rate command {key!r} names no camera of this engine; cameras: {', '.join(cameras) or '(none)'}"
        )
    return model, camera if at else None


def model_names_text(names: Iterable[str]) -> str:
    """The model-names topic's text: a JSON list, e.g. ``["foundation", "depth", "seg", "det"]``."""
    return json.dumps(list(names))


# --------------------------------------------------------------------------------------------- diagnostics
def _fmt(v: Any) -> str:
    if v is None:
        return "none"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.2f}"
    return str(v)


def model_status(name: str, m: Mapping[str, Any], prefix: str, hardware_id: str) -> Status:
    """One model's health from ``Engine.stats()["models"][name]``: OK; WARN while restarting or paused (also
    starting/loading); ERROR when failed for good or hung (thread mode, Note [Hung threads])."""
    state = str(m.get("state", "unknown"))
    target = m.get("target_hz")
    achieved = float(m.get("achieved_hz") or 0.0)
    tgt = "unlimited" if target is None else f"{target:g} Hz"
    lat = m.get("latency_ms") or {}
    paused = state == "paused" or target == 0
    if state in ("failed", "hung"):
        level, msg = ERROR, f"{state}: {m.get('last_error') or 'no error text'}"
    elif state == "restarting":
        level, msg = WARN, f"restarting after a crash ({m.get('restarts', 0)} restarts so far)"
    elif paused:
        level, msg = WARN, "paused (rate 0)"
    elif state in ("starting", "loading"):
        level, msg = WARN, f"{state}"
    else:
        level, msg = OK, f"{state}, {achieved:.1f} Hz (target {tgt})"
    values = [
        ("state", state),
        ("target_hz", "unlimited" if target is None else _fmt(float(target))),
        ("achieved_hz", _fmt(achieved)),
        ("runs", _fmt(m.get("runs", 0))),
        ("skipped", _fmt(m.get("skipped", 0))),
        ("drops", _fmt(m.get("dropped", 0))),
        ("errors", _fmt(m.get("errors", 0))),
        ("restarts", _fmt(m.get("restarts", 0))),
        ("latency_p50_ms", _fmt(lat.get("p50"))),
        ("latency_p99_ms", _fmt(lat.get("p99"))),
    ]
    return Status(level, f"{prefix}: {name}", msg, hardware_id, values)


# ------------------------------------------------------------------------------------------------ rejections
class Rejections:
    """Note [Rejection log]: bad inputs are counted and logged per reason, never one line per frame, never only once.

    The first rejection of each reason (:attr:`InputError.reason`: encoding, short_data, step, malformed ...) is
    logged at once with its full text, so a different later failure is never hidden behind the first one; after
    that each reason logs at most one line per ``every_s`` seconds, saying how many were not logged. ``recent()``
    names the reasons seen in the last ``recent_s`` seconds: the interface status in /diagnostics warns while it is
    not empty and so goes back to OK once good frames have flowed that long, instead of warning for the rest of the
    run. ``where`` starts each line (what was rejected, and by whom). Thread-safe; ``clock`` is for tests.
    """

    def __init__(
        self,
        where: str,
        logger: logging.Logger = log,
        every_s: float = 10.0,
        recent_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.where = where
        self.counts: collections.Counter[str] = collections.Counter()
        self._log, self.every_s, self.recent_s, self.clock = logger, every_s, recent_s, clock
        self._last: dict[str, float] = {}  # reason -> time of its newest rejection
        self._logged: dict[str, float] = {}  # reason -> time of its newest log line
        self._unlogged: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()

    def add(self, reason: str, text: str) -> None:
        now = self.clock()
        with self._lock:
            self.counts[reason] += 1
            self._last[reason] = now
            logged = self._logged.get(reason)
            if logged is not None and now - logged < self.every_s:
                self._unlogged[reason] += 1
                return
            self._logged[reason] = now
            more, self._unlogged[reason] = self._unlogged[reason], 0
            total = self.counts[reason]
        if logged is None:
            self._log.warning("%s (%s): %s", self.where, reason, text)
        else:
            self._log.warning(
                "%s (%s; %d in all, %d not logged since the last line): %s",
                self.where,
                reason,
                total,
                more,
                text,
            )

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def recent(self) -> list[str]:
        """The reasons rejected within the last ``recent_s`` seconds, sorted."""
        now = self.clock()
        with self._lock:
            return sorted(r for r, t in self._last.items() if now - t < self.recent_s)


# ---------------------------------------------------------------------------------------------- input link
#: A publisher matched this long with nothing received is reported (Note [Input link]).
SILENT_AFTER_S = 5.0


def receive_buffer_limit() -> int | None:
    """The largest socket receive buffer an unprivileged process gets (Linux ``net.core.rmem_max``); None where
    unknown."""
    try:
        with open("/proc/sys/net/core/rmem_max") as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return None


def receive_buffer_advice(limit: int | None, frame_bytes: int) -> str | None:
    """Note [Input link]: what to do when the UDP receive buffer cannot hold one input frame; None when it can.

    A best-effort sample (cameras publish with the sensor-data profile) arrives as a burst of UDP datagrams; the
    ones that do not fit the socket's receive buffer while the receiving thread is busy are dropped, and a sample
    missing one fragment is lost whole, without any count on either side (DDS reports no sample lost for it). On
    loopback a 1080p frame (6.2 MB) came through 36 of 150 times with cyclonedds' default 1 MB buffer and 113 of
    150 with 3 MB; all 150 with 4 MB. So the buffer must hold a whole frame. The kernel caps what a process asks
    for at ``net.core.rmem_max`` (Linux default 208 kB).
    """
    if limit is None or limit >= frame_bytes:
        return None
    want = 1 << max(2 * frame_bytes - 1, 1).bit_length()  # two frames, rounded up to a power of two
    return (
        f"the UDP receive buffer is limited to {limit} bytes (net.core.rmem_max), less than one {frame_bytes}-byte "
        f"input frame: best-effort frames are lost, uncounted, whenever the receiver falls behind; fix: "
        f"sudo sysctl -w net.core.rmem_max={want} (and in /etc/sysctl.d/ to keep it)"
    )


# ------------------------------------------------------------------------------------------- control path
class ControlLoop:
    """Note [Control path]: rate commands and /diagnostics have a thread of their own, shared by every transport.

    On the output thread they waited behind the writes of 8 MB images (a reliable write can block until a slow
    reader acknowledges): at 1080p /diagnostics went silent for 3-17 s, longer than diagnostic_aggregator's stale
    timeout, and rate commands, wanted most when the machine is overloaded, waited as long. This loop waits only for
    rate commands (``wait_commands(timeout)`` returns the (model, rate) pairs that arrived, waiting at most
    ``timeout`` s), applies each at once and publishes diagnostics right after it (the change is seen, and the
    diagnostics' stamp says when it was applied), and otherwise publishes diagnostics every ``period_s`` on a fixed
    schedule. It touches the engine only through ``set_rate`` and ``stats`` (shared-memory writes and reads), so it
    never waits for a frame or a result. ``before_diagnostics`` lets the transport refresh what only it knows (the
    input link: matched publishers, receive buffer) first.
    """

    def __init__(
        self,
        core: Ros2Core,
        publish: Callable[[DiagnosticsOut], None],
        wait_commands: Callable[[float], Iterable[tuple[str, str]]],
        *,
        period_s: float = 1.0,
        before_diagnostics: Callable[[], None] | None = None,
    ) -> None:
        if not period_s > 0:
            raise ValueError(f"diagnostics period must be > 0 s, got {period_s}")
        self.core, self.publish, self.wait_commands = core, publish, wait_commands
        self.period_s = period_s
        self.before_diagnostics = before_diagnostics

    def diagnostics_now(self) -> None:
        if self.before_diagnostics is not None:
            self.before_diagnostics()
        self.publish(self.core.diagnostics())

    def run(self, stop: threading.Event) -> None:
        """Until ``stop`` is set."""
        next_at = time.monotonic()
        while not stop.is_set():
            applied = False
            for key, value in self.wait_commands(max(0.0, min(next_at - time.monotonic(), 0.2))):
                try:
                    self.core.set_rate(key, value)
                    applied = True
                except ValueError as e:
                    log.warning("rate command {key: %r, value: %r} ignored: %s", key, value, e)
            now = time.monotonic()
            if applied or now >= next_at:
                self.diagnostics_now()
                # a fixed schedule; after a command (or a stall longer than a period) a period from now
                next_at = now + self.period_s if applied or now - next_at > self.period_s else next_at + self.period_s


# ------------------------------------------------------------------------------------------------- the core
class Ros2Core:
    """The engine behind a ROS 2 interface, with no middleware: messages in, neutral outputs out.

    A transport (DDS bridge, rclpy node) feeds input messages to :meth:`handle_image` / :meth:`handle_compressed`
    from its receive thread, publishes what :meth:`poll_outputs` returns from another thread, forwards rate
    commands to :meth:`set_rate`, and publishes :meth:`diagnostics` about once a second. Uses the public Engine API
    only (submit, results, set_rate, stats, head_info).

    Frames of any size go to the engine as they come, and every output is published at the camera's size, in its
    pixels, under its header (Note [Frame grid] in boundary.py). ``input_size="config"`` starts the engine at once
    with the config's ``input.height/width``; ``"first"`` starts it when the first message arrives, with the models
    at that message's size, so a camera's frames need no resizing (messages arriving during start-up are not seen).

    Several cameras (``cameras``: their names, one input topic each; or a config with ``cameras``): every message
    is handed in with its camera (``handle_image(msg, camera)``, from one thread per topic if need be), and each
    camera's outputs go out under its own namespace, ``<ns>/<camera>/<head>/...``, with that camera's input header.
    Rate commands may name ``head@camera``; /diagnostics has a status per camera.
    """

    def __init__(
        self,
        config: Any,
        *,
        namespace: str = "/vpengine",
        input_size: Literal["config", "first"] = "config",
        depth_color: bool = False,
        seg_overlay: bool = False,
        overrides: Sequence[str] = (),
        cameras: Sequence[str] | None = None,
    ) -> None:
        from vpengine.config import config_for_cameras

        if input_size not in ("config", "first"):
            raise ValueError(f"input_size must be 'config' or 'first', got {input_size!r}")
        self.config = config_for_cameras(config, list(cameras) if cameras else None, list(overrides), "input topics")
        self.namespace = normalize_namespace(namespace)
        self.input_size = input_size
        planner = self._new_engine(self.config)  # planned only: head metadata without starting anything
        self.model_names: list[str] = self.config.model_names()
        self.head_infos: dict[str, dict[str, Any]] = {h.name: planner.head_info(h.name) for h in self.config.heads}
        #: the engine's cameras, in priority order; with several, each has its own input topic and namespace
        self.cameras: list[str] = self.config.camera_names()
        self.several = len(self.cameras) > 1
        served = {c: [h for h in self.head_infos if c in self.config.model_cameras(h)] for c in self.cameras}
        self.topics, self.unmapped = plan_outputs(
            self.head_infos, self.namespace, depth_color, seg_overlay, served if self.several else None
        )
        for h in self.unmapped:
            log.warning("head %r has no ROS 2 message mapping (kind 'generic'); its outputs are not published", h)
        self._by_head: dict[tuple[str | None, str], list[OutputTopic]] = collections.defaultdict(list)
        for t in self.topics:
            self._by_head[(t.camera, t.head)].append(t)
        self.book = FrameBook(frames=16 * len(self.cameras) if seg_overlay else 0)
        self._next_fid = 0  # engine frame ids are ours, so a header is booked before its frame is submitted
        self.engine: Any = None
        self._engine_ready = threading.Event()
        self._start_lock = threading.Lock()
        self.counters: collections.Counter[str] = collections.Counter()
        #: with several cameras, each camera's input counters (received, submitted, superseded, rejected, not_ready)
        self.camera_counters: dict[str, collections.Counter[str]] = (
            {c: collections.Counter() for c in self.cameras} if self.several else {}
        )
        # input threads (one per camera's topic) count and submit under it; frame ids are allotted under it
        self._input_lock = threading.Lock()
        self.published: collections.Counter[str] = collections.Counter()
        #: Note [Rejection log]: input messages and outputs that could not be used, per reason
        self.rejected = Rejections("input message rejected")
        self.output_errors = Rejections("output not published")
        self.outputs_superseded: collections.Counter[str] = collections.Counter()
        # Note [Input link]: when a publisher of the input topic was matched (None: none is), the transport's
        # receive-buffer advice, and the largest input message seen (bytes)
        self._matched_since: float | None = None
        self._received_at_match = 0
        self._buffer_limit: int | None = None
        self._largest_input = 0
        self._link_logged: set[str] = set()
        #: CPU seconds (of the calling thread: time.thread_time, so neither waiting for data nor for the GIL counts)
        #: per stage: decode, submit (per input frame); results, convert (per output); transports add
        #: encode, write. Where the interface's time goes; reported in /diagnostics as busy_s.<stage>.
        self.busy: collections.Counter[str] = collections.Counter()
        self.hardware_id = f"vpengine {self.config.name} ({self.config.device})"
        self.status_prefix = self.namespace.strip("/").replace("/", ".") or "vpengine"

    def _new_engine(self, cfg: Any) -> Any:
        from vpengine.engine import Engine

        return Engine(cfg)

    # ------------------------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Start the engine now (``input_size="config"``); with ``"first"`` it starts on the first message."""
        if self.input_size == "config":
            self._start_engine(self.config)

    def _start_engine(self, cfg: Any) -> None:
        with self._start_lock:
            if self.engine is not None:
                return
            t0 = time.monotonic()
            eng = self._new_engine(cfg)
            eng.start()
            eng.results(0)  # start the result stream before the first frame goes in
            self.engine = eng
            self._engine_ready.set()
            log.info(
                "engine started in %.1f s (input %dx%d)",
                time.monotonic() - t0,
                cfg.input.width,
                cfg.input.height,
            )

    def wait_ready(self, timeout: float | None = None) -> bool:
        return self._engine_ready.wait(timeout)

    def stop(self) -> None:
        eng, self.engine = self.engine, None
        self._engine_ready.clear()
        if eng is not None:
            eng.stop()

    # --------------------------------------------------------------------------------------------- input
    def handle_image(self, msg: Any, camera: str | None = None) -> int | None:
        """Submit a sensor_msgs/Image from ``camera`` (None: the one camera). Returns the engine frame id, or None
        when rejected (counted and logged). Safe to call from one thread per camera."""
        return self._handle(msg, image_to_frame, camera)

    def handle_compressed(self, msg: Any, camera: str | None = None) -> int | None:
        """Submit a sensor_msgs/CompressedImage (jpeg/png). Returns the frame id, or None when rejected."""
        return self._handle(msg, compressed_to_frame, camera)

    def _count(self, key: str, camera: str | None, n: int = 1) -> None:
        with self._input_lock:
            self.counters[key] += n
            if camera in self.camera_counters:
                self.camera_counters[camera][key] += n  # type: ignore[index]

    def _handle(self, msg: Any, decode: Callable[[Any, str], np.ndarray], camera: str | None) -> int | None:
        self._count("received", camera)
        t0 = time.thread_time()
        try:
            header = Header.of(msg.header)
            frame = decode(msg, self.config.input.color)
            self.busy["decode"] += time.thread_time() - t0
        except InputError as e:
            self._reject(e.reason, str(e), camera)
            return None
        except (ValueError, AttributeError, TypeError) as e:  # not shaped like the message type at all
            self._reject("malformed", f"{type(e).__name__}: {e}", camera)
            return None
        self._largest_input = max(self._largest_input, as_uint8(msg.data).size)
        if self.engine is None:
            if self.input_size == "first":
                from vpengine.config import load_config

                h, w = frame.shape[:2]
                self._start_engine(load_config(self.config, [f"input.height={h}", f"input.width={w}"]))
            else:
                self._count("not_ready", camera)
                return None
        eng = self.engine
        if eng is None:  # stopped meanwhile
            self._count("not_ready", camera)
            return None
        bgr = None
        if self.book.keeps_frames:
            bgr = frame if eng.config.input.color == "bgr" else frame[..., ::-1]
        with self._input_lock:
            # The header goes into the book *before* the frame goes into the engine: a fast head's output can reach
            # the output thread before submit() even returns here, and must find its header (Note [Output headers]).
            fid = self._next_fid
            self._next_fid += 1
            self.book.add(fid, header, bgr)
            t0 = time.thread_time()
            try:
                eng.submit(frame, frame_id=fid, timestamp=header.seconds, camera=camera)
            except ValueError as e:
                error: ValueError | None = e
            else:
                error = None
                self.busy["submit"] += time.thread_time() - t0
        if error is not None:
            self._reject("engine", str(error), camera)
            return None
        self._count("submitted", camera)
        return fid

    # -------------------------------------------------------------------------------------------- output
    def poll_outputs(self, timeout: float = 0.1) -> list[tuple[OutputTopic, Payload]]:
        """The head outputs since the last call as (topic, message), oldest first; waits up to ``timeout``.

        Note [Output QoS]: when the engine takes the newest frame (``input_mode: latest``), only each head's newest
        result is converted and published; older ones that waited for the output thread (it was writing) are
        counted in ``outputs_superseded.<head>``. Publishing them would only put stale images in front of the
        fresh one. With ``input_mode: fifo`` every result goes out, in order."""
        eng = self.engine
        if eng is None:
            self._engine_ready.wait(timeout)
            return []
        out: list[tuple[OutputTopic, Payload]] = []
        t0 = time.thread_time()
        results = eng.results(timeout=timeout)
        self.busy["results"] += time.thread_time() - t0  # the engine API's copies out of its mailboxes
        if self.config.foundation_model.input_mode != "fifo":
            newest = {(r.camera, r.head): r for r in results}  # results are oldest first
            for r in results:
                if newest[(r.camera, r.head)] is not r:
                    self.outputs_superseded[r.head] += 1
            results = [r for r in results if newest[(r.camera, r.head)] is r]
        for r in results:
            topics = self._by_head.get((r.camera if self.several else None, r.head))
            if not topics:
                continue
            header = self.book.header(r.frame_id)
            if header is None:  # see Note [Output headers]
                self.counters["header_fallbacks"] += 1
                header = Header.from_seconds(r.capture_time)
            frame = self.book.frame(r.frame_id)
            info = self.head_infos[r.head]
            t0 = time.thread_time()
            for t in topics:
                try:
                    p = payload_for(t, r.outputs, info, header, frame)
                except (ValueError, KeyError) as e:
                    self.output_errors.add(t.role, f"head {r.head!r}: {e}")
                    continue
                if p is None:
                    self.counters["overlays_skipped"] += 1
                    continue
                out.append((t, p))
            self.busy["convert"] += time.thread_time() - t0
        return out

    def _reject(self, reason: str, text: str, camera: str | None = None) -> None:
        self._count("rejected", camera)
        self.rejected.add(reason, text if camera is None else f"camera {camera!r}: {text}")

    def reject_message(self, reason: str, text: str, camera: str | None = None) -> None:
        """A transport received a message it could not even parse (e.g. malformed CDR): counted as received and
        rejected, and logged per Note [Rejection log]."""
        self._count("received", camera)
        self._reject(reason, text, camera)

    def note_publishers(self, n: int) -> None:
        """The transport's count of publishers matched on the input topic (Note [Input link])."""
        if n <= 0:
            self._matched_since = None
        elif self._matched_since is None:
            self._matched_since = time.monotonic()
            self._received_at_match = self.counters["received"]

    def note_receive_buffer(self, limit: int | None) -> None:
        """The largest receive buffer the transport's sockets can have, in bytes (Note [Input link])."""
        self._buffer_limit = limit

    def link_warnings(self) -> list[str]:
        """Note [Input link]: what is wrong with the way in; each kind is logged once, when first seen."""
        found: dict[str, str] = {}
        want = self._largest_input or 3 * self.config.input.height * self.config.input.width
        advice = receive_buffer_advice(self._buffer_limit, want)
        since = self._matched_since
        if (
            since is not None
            and self.counters["received"] == self._received_at_match
            and time.monotonic() - since >= SILENT_AFTER_S
        ):
            found["silent"] = (
                f"a publisher has been matched for {time.monotonic() - since:.0f} s and no input message "
                "arrived: large samples are probably lost on the way in"
                + ("" if advice else " (check the transport's receive buffer, fragment and sample size settings)")
            )
        if advice:
            found["buffer"] = advice
        for kind, text in found.items():
            if kind not in self._link_logged:
                self._link_logged.add(kind)
                log.warning("input link: %s", text)
        return list(found.values())

    def count_superseded(self, n: int, camera: str | None = None) -> None:
        """``n`` input messages were received but not submitted because a newer one was already waiting."""
        self._count("received", camera, n)
        self._count("superseded", camera, n)

    def count_published(self, topic: OutputTopic) -> None:
        self.published[topic.topic] += 1

    # ------------------------------------------------------------------------------------------- control
    def set_rate(self, key: str, value: str) -> tuple[str, float | None]:
        """Apply a rate command (model name, or ``model@camera`` for one camera's rate; rate text). Raises ValueError
        naming what is wrong; counted."""
        try:
            key, hz = parse_rate_command(key, value, self.model_names, self.cameras)
            model, camera = model_at(key, self.model_names, self.cameras)
            if self.engine is None:
                raise ValueError("the engine has not started yet (it starts on the first input message)")
            self.engine.set_rate(model, hz, camera=camera)
        except (ValueError, KeyError) as e:
            self.counters["rate_commands_rejected"] += 1
            raise ValueError(str(e.args[0]) if isinstance(e, KeyError) and e.args else str(e)) from None
        self.counters["rate_commands"] += 1
        log.info("rate of %s set to %s", key, "unlimited" if hz is None else f"{hz:g} Hz")
        return key, hz

    def set_rate_hz(self, model: str, hz: float | None) -> tuple[str, float | None]:
        """Apply a numeric rate (services): Hz >= 0 (0 pauses); None, a negative number or inf = unlimited."""
        if hz is not None and math.isnan(hz):
            self.counters["rate_commands_rejected"] += 1
            raise ValueError(f"rate for {model!r} is NaN; accepted: Hz >= 0, or negative/inf for no limit")
        unlimited = hz is None or hz < 0 or math.isinf(hz)
        return self.set_rate(model, "max" if unlimited else repr(float(hz)))  # type: ignore[arg-type]

    def diagnostics(self, now: float | None = None) -> DiagnosticsOut:
        """One status per model (see :func:`model_status`), one for the interface itself and, with several cameras,
        one per camera (``<prefix>: camera <name>``: its input counters and its models' rates and counts)."""
        t = time.time() if now is None else now
        header = Header.from_seconds(t)  # diagnostics describe "now", not an input frame
        status: list[Status] = []
        eng = self.engine
        stats = eng.stats() if eng is not None else {}
        models = stats.get("models", {})
        results = stats.get("results", {})
        for name in self.model_names:
            if name in models:
                status.append(model_status(name, models[name], self.status_prefix, self.hardware_id))
            else:
                status.append(Status(WARN, f"{self.status_prefix}: {name}", "engine not started", self.hardware_id))
        c = self.counters
        values = [
            (k, str(c[k]))
            for k in (
                "received",
                "submitted",
                "superseded",
                "rejected",
                "not_ready",
                "header_fallbacks",
                "overlays_skipped",
                "rate_commands",
                "rate_commands_rejected",
            )
        ]
        values += [(f"rejected.{r}", str(n)) for r, n in sorted(self.rejected.counts.items())]
        values += [(f"output_errors.{r}", str(n)) for r, n in sorted(self.output_errors.counts.items())]
        values += [(f"results_missed.{h}", str(r.get("missed", 0))) for h, r in results.items()]
        values += [(f"outputs_superseded.{h}", str(self.outputs_superseded[h])) for h in results]
        values += [(f"published:{t.topic}", str(self.published[t.topic])) for t in self.topics]
        values += [(f"busy_s.{k}", f"{v:.3f}") for k, v in sorted(self.busy.items())]
        if self._buffer_limit is not None:
            values.append(("receive_buffer_limit_bytes", str(self._buffer_limit)))
        # Note [Rejection log]: WARN while rejections are recent, OK again once good frames have flowed a while
        problems = []
        for what, rej in (("inputs rejected", self.rejected), ("outputs not published", self.output_errors)):
            recent = rej.recent()
            if recent:
                problems.append(f"{what} in the last {rej.recent_s:g} s ({', '.join(recent)})")
        problems += self.link_warnings()
        msg = "; ".join([f"{c['submitted']} frames in, {sum(self.published.values())} messages out", *problems])
        status.append(
            Status(WARN if problems else OK, f"{self.status_prefix}: interface", msg, self.hardware_id, values)
        )
        per_camera = stats.get("cameras", {})
        for camera, counts in self.camera_counters.items():  # several cameras: each one's input and models
            values = [(k, str(counts[k])) for k in ("received", "submitted", "superseded", "rejected", "not_ready")]
            for model, m in per_camera.get(camera, {}).items():
                target = m.get("target_hz")
                values += [
                    (f"{model}.target_hz", "unlimited" if target is None else _fmt(float(target))),
                    (f"{model}.achieved_hz", _fmt(float(m.get("achieved_hz") or 0.0))),
                    *((f"{model}.{k}", _fmt(m.get(k, 0))) for k in ("runs", "skipped", "late", "deferred")),
                ]
            status.append(
                Status(
                    OK,
                    f"{self.status_prefix}: camera {camera}",
                    f"{counts['submitted']} frames in of {counts['received']} received",
                    self.hardware_id,
                    values,
                )
            )
        return DiagnosticsOut(header, status)
