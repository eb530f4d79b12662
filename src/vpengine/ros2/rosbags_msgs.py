"""rosbags type stores for the ROS 2 distributions we write, with vision_msgs 4.x added, and neutral outputs as
rosbags message objects.

rosbags ships the common_interfaces of each distribution (sensor_msgs, std_msgs, geometry_msgs, diagnostic_msgs) but
not vision_msgs; :data:`VISION_MSGS` declares the 4.x definitions (the version in the Humble and Jazzy releases, see
:mod:`vpengine.ros2.dds_types`), so bags carry a full message definition for Detection2DArray.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from vpengine.ros2.messages import DetectionsOut, Header, ImageOut

#: distribution -> (rosbags store name, rosbag2 metadata version written)
DISTROS: dict[str, tuple[str, int]] = {
    # rosbags writes versions 8 and 9 only. Humble's own rosbag2 writes version 5; version 8 is the closest that
    # keeps Humble's QoS serialization (9 changed it), with Humble's message definitions and hashes.
    "humble": ("ROS2_HUMBLE", 8),
    "jazzy": ("ROS2_JAZZY", 9),
}

VISION_MSGS: dict[str, str] = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/Detection2D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\nvision_msgs/BoundingBox2D bbox\n"
        "string id\n"
    ),
    "vision_msgs/msg/Detection2DArray": "std_msgs/Header header\nvision_msgs/Detection2D[] detections\n",
}


@functools.lru_cache(maxsize=8)
def typestore(distro: str = "jazzy") -> Any:
    """The rosbags Typestore of ``distro`` (humble | jazzy) with vision_msgs 4.x registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if distro not in DISTROS:
        raise ValueError(f"ROS 2 distribution {distro!r} is not supported; accepted: {', '.join(DISTROS)}")
    ts = get_typestore(getattr(Stores, DISTROS[distro][0]))
    types: dict[str, Any] = {}
    for name, text in VISION_MSGS.items():
        types.update(get_types_from_msg(text, name))
    ts.register(types)
    return ts


def header_msg(ts: Any, h: Header) -> Any:
    T = ts.types
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=h.sec, nanosec=h.nanosec), frame_id=h.frame_id
    )


def image_msg(ts: Any, img: ImageOut) -> Any:
    return ts.types["sensor_msgs/msg/Image"](
        header=header_msg(ts, img.header),
        height=img.height,
        width=img.width,
        encoding=img.encoding,
        is_bigendian=img.is_bigendian,
        step=img.step,
        data=img.data,
    )


def compressed_msg(ts: Any, header: Header, fmt: str, data: np.ndarray) -> Any:
    """A sensor_msgs/CompressedImage of already encoded bytes (``fmt``: image_transport's, e.g. ``"bgr8; jpeg
    compressed bgr8"``)."""
    return ts.types["sensor_msgs/msg/CompressedImage"](header=header_msg(ts, header), format=fmt, data=data)


def detections_msg(ts: Any, d: DetectionsOut) -> Any:
    T = ts.types
    header = header_msg(ts, d.header)
    dets = []
    for det in d.detections:
        pose = T["geometry_msgs/msg/PoseWithCovariance"](
            pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            ),
            covariance=np.zeros(36, np.float64),
        )
        hyp = T["vision_msgs/msg/ObjectHypothesisWithPose"](
            hypothesis=T["vision_msgs/msg/ObjectHypothesis"](class_id=det.class_id, score=det.score),
            pose=pose,
        )
        bbox = T["vision_msgs/msg/BoundingBox2D"](
            center=T["vision_msgs/msg/Pose2D"](
                position=T["vision_msgs/msg/Point2D"](x=det.center_x, y=det.center_y), theta=0.0
            ),
            size_x=det.size_x,
            size_y=det.size_y,
        )
        dets.append(T["vision_msgs/msg/Detection2D"](header=header, results=[hyp], bbox=bbox, id=""))
    return T["vision_msgs/msg/Detection2DArray"](header=header, detections=dets)


def to_rosbags(ts: Any, payload: ImageOut | DetectionsOut) -> Any:
    """A neutral output as a rosbags message object of ``ts``."""
    if isinstance(payload, ImageOut):
        return image_msg(ts, payload)
    if isinstance(payload, DetectionsOut):
        return detections_msg(ts, payload)
    raise TypeError(f"no rosbags message for {type(payload).__name__}")
