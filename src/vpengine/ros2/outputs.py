"""What each head publishes: its output topics (by the head's kind), and the message of each topic for a result.

No middleware here; the transports publish what :func:`payload_for` builds. Note [Output QoS] says how the output
topics keep fresh.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from vpengine.ros2.messages import DETECTIONS_TYPE, IMAGE_TYPE, Detection, DetectionsOut, Header, ImageOut
from vpengine.visualize import head_kind

#: QoS profiles of the output topics (Note [Output QoS]); the first is the default.
OUTPUT_QOS = ("latest", "default")

# Note [Output QoS]: outputs must stay fresh when a subscriber or the machine cannot keep up. Measured with 1080p
# frames at 30 Hz, a subscriber that copies each image and a busy CPU (benchmarks/results/
# ros2_bridge_throughput.json), two queues made outputs seconds old: (1) a reliable keep-last-10 writer keeps up to
# ten unacknowledged 8 MB images per topic and a write blocks while a slow reader catches up, so (2) results waited
# for the output thread in the engine's result stream and went out in order, each older than the last. So: outputs
# are reliable (a best-effort writer matches no reliable subscriber, ROS 2's default) but keep last 1 ("latest"),
# so a writer holds one image and never more; and with newest-wins input (input_mode: latest) the output thread
# publishes only each head's newest result (Ros2Core.poll_outputs), counting the ones it skips. ROS 2's default profile
# stays available ("default", for recording every output).


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
