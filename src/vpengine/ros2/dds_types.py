"""ROS 2 message types declared for CycloneDDS, exactly as ROS 2 puts them on the wire.

ROS 2 (rosidl + rmw_cyclonedds) maps a message ``pkg/msg/Type`` to the DDS type ``pkg::msg::dds_::Type_`` (a final
struct, fields in declaration order) and sends it as XCDR1 little-endian CDR. The classes below declare the same
structs with ``cyclonedds.idl``, so a cyclonedds DataWriter/DataReader of these classes interoperates with ROS 2
nodes. Field types follow the ROS IDL mapping: ``uint8[]`` -> ``sequence<uint8>``, ``byte`` -> ``octet``,
``float64[36]`` -> ``double[36]``, ``string`` -> ``string``.

Versions matched (the definitions are the same in Humble and Jazzy unless noted):

* builtin_interfaces/Time, std_msgs/Header, std_msgs/String, sensor_msgs/Image, sensor_msgs/CompressedImage,
  geometry_msgs/Point, Quaternion, Pose, PoseWithCovariance, diagnostic_msgs/KeyValue, DiagnosticStatus,
  DiagnosticArray: common_interfaces (Humble 4.x, Jazzy 5.3).
* vision_msgs: **4.x** (ros-perception/vision_msgs 4.0 and later; the Humble and Jazzy releases ship 4.1):
  ``BoundingBox2D.center`` is ``vision_msgs/Pose2D {Point2D position {x, y}, float64 theta}`` (3.x used
  ``geometry_msgs/Pose2D {x, y, theta}``, which has the same wire layout but another type name), and
  ``Detection2D`` is ``{Header header, ObjectHypothesisWithPose[] results, BoundingBox2D bbox, string id}`` with
  ``ObjectHypothesisWithPose {ObjectHypothesis hypothesis {string class_id, float64 score},
  geometry_msgs/PoseWithCovariance pose}``.

Big images are written and read through :mod:`vpengine.ros2.cdr` (same bytes, no per-pixel Python objects); these
classes name the topics' types and carry every other message.
"""

# No `from __future__ import annotations`: cyclonedds resolves field types from the live annotations.
from dataclasses import dataclass, field

from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t

# DDS type names end in "_", as rosidl generates them (sensor_msgs::msg::dds_::Image_).


def _q_identity() -> "Quaternion_":
    return Quaternion_(0.0, 0.0, 0.0, 1.0)


@dataclass
class Time_(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32 = 0
    nanosec: t.uint32 = 0


@dataclass
class Header_(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time_ = field(default_factory=Time_)
    frame_id: str = ""


@dataclass
class String_(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data: str = ""


@dataclass
class Image_(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
    header: Header_ = field(default_factory=Header_)
    height: t.uint32 = 0
    width: t.uint32 = 0
    encoding: str = ""
    is_bigendian: t.uint8 = 0
    step: t.uint32 = 0
    data: t.sequence[t.uint8] = field(default_factory=list)


@dataclass
class CompressedImage_(IdlStruct, typename="sensor_msgs::msg::dds_::CompressedImage_"):
    header: Header_ = field(default_factory=Header_)
    format: str = ""
    data: t.sequence[t.uint8] = field(default_factory=list)


@dataclass
class Point_(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Quaternion_(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0
    w: t.float64 = 1.0  # ROS 2 default: the identity rotation


@dataclass
class Pose_(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point_ = field(default_factory=Point_)
    orientation: Quaternion_ = field(default_factory=_q_identity)


@dataclass
class PoseWithCovariance_(IdlStruct, typename="geometry_msgs::msg::dds_::PoseWithCovariance_"):
    pose: Pose_ = field(default_factory=Pose_)
    covariance: t.array[t.float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class Point2D_(IdlStruct, typename="vision_msgs::msg::dds_::Point2D_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0


@dataclass
class Pose2D_(IdlStruct, typename="vision_msgs::msg::dds_::Pose2D_"):
    position: Point2D_ = field(default_factory=Point2D_)
    theta: t.float64 = 0.0


@dataclass
class BoundingBox2D_(IdlStruct, typename="vision_msgs::msg::dds_::BoundingBox2D_"):
    center: Pose2D_ = field(default_factory=Pose2D_)
    size_x: t.float64 = 0.0
    size_y: t.float64 = 0.0


@dataclass
class ObjectHypothesis_(IdlStruct, typename="vision_msgs::msg::dds_::ObjectHypothesis_"):
    class_id: str = ""
    score: t.float64 = 0.0


@dataclass
class ObjectHypothesisWithPose_(IdlStruct, typename="vision_msgs::msg::dds_::ObjectHypothesisWithPose_"):
    hypothesis: ObjectHypothesis_ = field(default_factory=ObjectHypothesis_)
    pose: PoseWithCovariance_ = field(default_factory=PoseWithCovariance_)


@dataclass
class Detection2D_(IdlStruct, typename="vision_msgs::msg::dds_::Detection2D_"):
    header: Header_ = field(default_factory=Header_)
    results: t.sequence[ObjectHypothesisWithPose_] = field(default_factory=list)
    bbox: BoundingBox2D_ = field(default_factory=BoundingBox2D_)
    id: str = ""


@dataclass
class Detection2DArray_(IdlStruct, typename="vision_msgs::msg::dds_::Detection2DArray_"):
    header: Header_ = field(default_factory=Header_)
    detections: t.sequence[Detection2D_] = field(default_factory=list)


@dataclass
class KeyValue_(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str = ""
    value: str = ""


@dataclass
class DiagnosticStatus_(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level: t.byte = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: t.sequence[KeyValue_] = field(default_factory=list)


@dataclass
class DiagnosticArray_(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header_ = field(default_factory=Header_)
    status: t.sequence[DiagnosticStatus_] = field(default_factory=list)


#: ROS message type name -> DDS class
BY_ROS_TYPE: dict[str, type[IdlStruct]] = {
    "builtin_interfaces/msg/Time": Time_,
    "std_msgs/msg/Header": Header_,
    "std_msgs/msg/String": String_,
    "sensor_msgs/msg/Image": Image_,
    "sensor_msgs/msg/CompressedImage": CompressedImage_,
    "geometry_msgs/msg/Point": Point_,
    "geometry_msgs/msg/Quaternion": Quaternion_,
    "geometry_msgs/msg/Pose": Pose_,
    "geometry_msgs/msg/PoseWithCovariance": PoseWithCovariance_,
    "vision_msgs/msg/Point2D": Point2D_,
    "vision_msgs/msg/Pose2D": Pose2D_,
    "vision_msgs/msg/BoundingBox2D": BoundingBox2D_,
    "vision_msgs/msg/ObjectHypothesis": ObjectHypothesis_,
    "vision_msgs/msg/ObjectHypothesisWithPose": ObjectHypothesisWithPose_,
    "vision_msgs/msg/Detection2D": Detection2D_,
    "vision_msgs/msg/Detection2DArray": Detection2DArray_,
    "diagnostic_msgs/msg/KeyValue": KeyValue_,
    "diagnostic_msgs/msg/DiagnosticStatus": DiagnosticStatus_,
    "diagnostic_msgs/msg/DiagnosticArray": DiagnosticArray_,
}


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (the rosidl/rmw naming)."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"
