"""ROS 2 message types as neutral objects, and decoding the two image inputs.

Messages are read duck-typed (``msg.height``, ``msg.encoding``, ``msg.data``, ``msg.header.stamp.sec`` ...), so a
cyclonedds IDL object, an rclpy message, a rosbags message or an :class:`ImageOut` decoded by
:func:`vpengine.ros2.cdr.decode_image` all work. What goes out is built as a small neutral object (:class:`ImageOut`,
:class:`DetectionsOut`, :class:`vpengine.ros2.diagnostics.DiagnosticsOut`) that each transport turns into its own
message objects or bytes. No middleware here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

#: sensor_msgs/Image encodings accepted as input, with their channel counts.
INPUT_ENCODINGS: dict[str, int] = {"rgb8": 3, "bgr8": 3, "mono8": 1}
#: sensor_msgs/CompressedImage codecs accepted as input (decoded by OpenCV).
COMPRESSED_CODECS = ("jpeg", "png")

IMAGE_TYPE = "sensor_msgs/msg/Image"
COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
DETECTIONS_TYPE = "vision_msgs/msg/Detection2DArray"


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


# ------------------------------------------------------------------------------------------------ messages
@dataclass
class ImageOut:
    """A sensor_msgs/Image, to publish (:func:`vpengine.ros2.outputs.image_out`) or as received
    (:func:`vpengine.ros2.cdr.decode_image`); ``data`` is a flat uint8 view of the pixels, no copy (of received
    bytes: read-only)."""

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
