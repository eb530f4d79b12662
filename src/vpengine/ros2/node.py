"""An rclpy node for machines with ROS 2 installed: the bridge's topics, plus services.

::

    python -m vpengine.ros2.node --ros-args -p config:=configs/tiny.yaml -p input_topic:=/camera/image_raw

Same topics, types, QoS and header rules as the DDS bridge (:mod:`vpengine.ros2.bridge`); every decision about
content (decoding, output topics, input headers on outputs, rate parsing, diagnostics) is made by
:class:`vpengine.ros2.core.Ros2Core`, shared with the bridge. This module only moves messages between rclpy and the
core. NOT EXERCISED HERE: rclpy cannot be installed on the development machine; see docs/ros2.md.

Services. The node serves the interface of the VPEngine paper's ROS node (nasa-jpl/visual-perception-engine) when a
package providing it is installed (``vpengine_interfaces``, or the paper's own ``vp_engine_ros``)::

    # ChangeModelRate.srv
    string model_name
    float64 new_rate      # Hz; 0 pauses; negative or inf: no limit (NaN is refused)
    ---
    bool success

    # GetModelNames.srv
    ---
    string[] model_names

Without such a package it falls back to standard interfaces: ``~/get_model_names`` (std_srvs/srv/Trigger; the
names as a JSON list in ``message``), one ROS parameter per model, ``rate.<model>`` (double, Hz; negative = no
limit), set with ``ros2 param set /vpengine rate.depth 5``, and one per head, ``priority.<head>`` (integer,
checks.MIN_PRIORITY to MAX_PRIORITY, higher more important), set with ``ros2 param set /vpengine priority.depth 10``.
The ``<ns>/set_rate`` and ``<ns>/set_priority`` topics (diagnostic_msgs/KeyValue) and the latched
``<ns>/model_names`` topic work in both cases.

Heads are added and removed while the node runs through the ``<ns>/add_head`` and ``<ns>/remove_head`` topics
(std_msgs/String), each outcome on the latched ``<ns>/head_events`` (Note [Head commands] in
:mod:`vpengine.ros2.heads`), as on the bridge; and, when the interface package has them, through services that
answer with the outcome (there is no standard service type that carries a text and answers with one)::

    # AddHead.srv     (served at ~/add_head)
    string config         # the head's config as under heads: in a config file, YAML or JSON
    ---
    bool success
    string message        # what was done, or the engine's error

    # RemoveHead.srv  (served at ~/remove_head)
    string name
    ---
    bool success
    string message

Parameters: ``config`` (required), ``input_topic`` (/camera/image_raw), ``input_topics`` (several cameras: a string
array of NAME=TOPIC, each camera's outputs under ``<output_namespace>/<NAME>/``), ``compressed`` (false), ``input_qos``
(sensor | default), ``output_qos`` (latest | default, see Note [Output QoS] in :mod:`vpengine.ros2.outputs`),
``output_namespace`` (/vpengine), ``depth_color`` / ``seg_overlay`` (false), ``input_size`` (config | first),
``overrides`` (string array of KEY=VALUE).
"""

from __future__ import annotations

import array
import importlib
import json
import logging
import queue
import sys
import threading
from typing import Any

from vpengine import checks
from vpengine.ros2.control import ControlLoop, model_names_text
from vpengine.ros2.core import Ros2Core, input_topics
from vpengine.ros2.diagnostics import DiagnosticsOut
from vpengine.ros2.heads import HEAD_COMMANDS, HeadCommands, HeadOutcome
from vpengine.ros2.messages import DETECTIONS_TYPE, DetectionsOut, Header, ImageOut
from vpengine.ros2.outputs import OUTPUT_QOS

log = logging.getLogger("vpengine.ros2.node")

#: packages searched, in order, for ChangeModelRate / GetModelNames
SERVICE_PACKAGES = ("vpengine_interfaces", "vp_engine_ros")


def _require_rclpy() -> Any:
    try:
        return importlib.import_module("rclpy")
    except ImportError:
        raise RuntimeError(
            "rclpy is not installed (source a ROS 2 installation, e.g. /opt/ros/jazzy/setup.bash, in a Python that "
            "also has vpengine); without ROS 2, `vpengine ros2` runs the same topics over CycloneDDS"
        ) from None


def find_services(names: tuple[str, ...] = ("ChangeModelRate", "GetModelNames")) -> tuple[Any, ...] | None:
    """The service types ``names`` (by default ChangeModelRate, GetModelNames; the head commands: AddHead,
    RemoveHead) from the first installed package that has them all, else None."""
    for pkg in SERVICE_PACKAGES:
        try:
            srv = importlib.import_module(f"{pkg}.srv")
            return tuple(getattr(srv, n) for n in names)
        except (ImportError, AttributeError):
            continue
    return None


# ------------------------------------------------------------------------------------ core output -> rclpy
def ros_header(h: Header) -> Any:
    from builtin_interfaces.msg import Time
    from std_msgs.msg import Header as RosHeader

    return RosHeader(stamp=Time(sec=h.sec, nanosec=h.nanosec), frame_id=h.frame_id)


def ros_image(p: ImageOut) -> Any:
    from sensor_msgs.msg import Image

    data = array.array("B")
    data.frombytes(p.data)  # one memcpy; rclpy's fast path for uint8[] is array.array('B'), not bytes or lists
    return Image(
        header=ros_header(p.header),
        height=p.height,
        width=p.width,
        encoding=p.encoding,
        is_bigendian=p.is_bigendian,
        step=p.step,
        data=data,
    )


def ros_detections(p: DetectionsOut) -> Any:
    from vision_msgs.msg import (
        BoundingBox2D,
        Detection2D,
        Detection2DArray,
        ObjectHypothesis,
        ObjectHypothesisWithPose,
        Point2D,
        Pose2D,
    )

    header = ros_header(p.header)
    return Detection2DArray(
        header=header,
        detections=[
            Detection2D(
                header=header,
                results=[ObjectHypothesisWithPose(hypothesis=ObjectHypothesis(class_id=d.class_id, score=d.score))],
                bbox=BoundingBox2D(
                    center=Pose2D(position=Point2D(x=d.center_x, y=d.center_y), theta=0.0),
                    size_x=d.size_x,
                    size_y=d.size_y,
                ),
                id="",
            )
            for d in p.detections
        ],
    )


def ros_diagnostics(d: DiagnosticsOut) -> Any:
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    return DiagnosticArray(
        header=ros_header(d.header),
        status=[
            DiagnosticStatus(
                level=bytes([s.level]),  # `byte` fields are bytes of length 1 in rclpy
                name=s.name,
                message=s.message,
                hardware_id=s.hardware_id,
                values=[KeyValue(key=k, value=v) for k, v in s.values],
            )
            for s in d.status
        ],
    )


# ------------------------------------------------------------------------------------------------ the node
def build_node(argv: list[str] | None = None) -> Any:
    """Create the node (rclpy must be initialised). Returns it; its ``shutdown()`` stops the engine."""
    _require_rclpy()
    from diagnostic_msgs.msg import DiagnosticArray, KeyValue
    from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
    from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import CompressedImage, Image
    from std_msgs.msg import String

    class VpengineNode(Node):  # type: ignore[misc, valid-type]
        def __init__(self) -> None:
            super().__init__("vpengine")
            p = self.declare_parameter
            config = p("config", "").value
            if not config:
                raise RuntimeError("parameter 'config' (an engine config file) is required")
            input_topic = p("input_topic", "/camera/image_raw").value
            # several cameras: NAME=TOPIC each (a STRING_ARRAY with no default, as overrides below)
            given = [str(t) for t in (p("input_topics", Parameter.Type.STRING_ARRAY).value or []) if t]
            topics = input_topics(given) if given else input_topic
            compressed = bool(p("compressed", False).value)
            input_qos = p("input_qos", "sensor").value
            if input_qos not in ("sensor", "default"):
                raise ValueError(f"parameter input_qos={input_qos!r}; accepted: sensor, default")
            output_qos = p("output_qos", OUTPUT_QOS[0]).value
            if output_qos not in OUTPUT_QOS:
                raise ValueError(f"parameter output_qos={output_qos!r}; accepted: {', '.join(OUTPUT_QOS)}")
            self.core = Ros2Core(
                config,
                namespace=p("output_namespace", "/vpengine").value,
                input_size=p("input_size", "config").value,
                depth_color=bool(p("depth_color", False).value),
                seg_overlay=bool(p("seg_overlay", False).value),
                # a STRING_ARRAY with no default: rclpy cannot infer the type of an empty list
                overrides=[str(o) for o in (p("overrides", Parameter.Type.STRING_ARRAY).value or []) if o],
                cameras=list(topics) if isinstance(topics, dict) else None,
            )
            core = self.core
            core.start()
            default_qos = QoSProfile(depth=10)
            out_qos = QoSProfile(depth=1 if output_qos == "latest" else 10)  # reliable, volatile
            latched = QoSProfile(
                depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE
            )
            self._out_qos = out_qos
            self._pubs: dict[str, Any] = {}
            self._writing = threading.Lock()  # held while publishing an output and while closing a head's topics
            self._open_topics(core.topics)
            self._diag = self.create_publisher(DiagnosticArray, "/diagnostics", default_qos)
            self._names = self.create_publisher(String, f"{core.namespace}/model_names", latched)
            self._names.publish(String(data=model_names_text(core.model_names)))
            self._head_events = self.create_publisher(String, f"{core.namespace}/head_events", latched)
            # Note [Control path] (vpengine.ros2.control): commands only queue here (callbacks of the
            # executor); the core's control loop applies them and publishes /diagnostics on its own thread. Input has
            # a callback group of its own, so a MultiThreadedExecutor never holds a command or a service call behind
            # a frame's decode.
            self._commands: queue.SimpleQueue[tuple[str, str, str]] = queue.SimpleQueue()
            control_group = MutuallyExclusiveCallbackGroup()
            for kind in ("rate", "priority"):
                self.create_subscription(
                    KeyValue,
                    f"{core.namespace}/set_{kind}",
                    lambda m, k=kind: self._commands.put((k, m.key, m.value)),
                    default_qos,
                    callback_group=control_group,
                )
            for kind in HEAD_COMMANDS:  # Note [Head commands]: queued here, carried out on the head thread
                self.create_subscription(
                    String,
                    f"{core.namespace}/{kind}",
                    lambda m, k=kind: self._commands.put((k, "", m.data)),
                    default_qos,
                    callback_group=control_group,
                )
            in_qos = qos_profile_sensor_data if input_qos == "sensor" else default_qos
            self._input_topics: list[str] = []
            inputs: dict[str | None, str] = {None: topics} if isinstance(topics, str) else dict(topics)
            for camera, topic in inputs.items():
                if compressed and not topic.rstrip("/").endswith("/compressed"):
                    topic = f"{topic.rstrip('/')}/compressed"
                self._input_topics.append(topic)
                handle = core.handle_compressed if compressed else core.handle_image
                # a group per camera: one camera's decode never holds another's frames back
                self.create_subscription(
                    CompressedImage if compressed else Image,
                    topic,
                    lambda m, h=handle, c=camera: h(m, c),
                    in_qos,
                    callback_group=MutuallyExclusiveCallbackGroup(),
                )
            self._heads = HeadCommands(core, self._open_topics, self._close_topics, self._publish_head_outcome)
            self._services(control_group)
            self._stop = threading.Event()
            self._control = ControlLoop(
                core,
                lambda d: self._diag.publish(ros_diagnostics(d)),
                self._wait_commands,
                before_diagnostics=lambda: core.note_publishers(
                    sum(self.count_publishers(t) for t in self._input_topics)
                ),
                heads=self._heads,
            )
            self._threads = [
                threading.Thread(target=self._output_loop, name="vpengine-outputs", daemon=True),
                threading.Thread(target=self._control.run, args=(self._stop,), name="vpengine-control", daemon=True),
                threading.Thread(target=self._heads.run, args=(self._stop,), name="vpengine-heads", daemon=True),
            ]
            for th in self._threads:
                th.start()

        def _open_topics(self, topics: list[Any]) -> None:
            for t in topics:
                kind = _detection_type() if t.msgtype == DETECTIONS_TYPE else Image
                self._pubs[t.topic] = self.create_publisher(kind, t.topic, self._out_qos)

        def _close_topics(self, topics: list[Any]) -> None:
            with self._writing:  # never under a publish in progress
                for t in topics:
                    self.destroy_publisher(self._pubs.pop(t.topic))

        def _publish_head_outcome(self, outcome: HeadOutcome) -> None:
            self._head_events.publish(String(data=outcome.text()))
            if outcome.ok:
                self._names.publish(String(data=model_names_text(outcome.model_names)))
            self._control.diagnostics_now()

        def _head_services(self) -> None:
            found = find_services(("AddHead", "RemoveHead"))
            if found is None:
                return
            add, remove = found
            group = MutuallyExclusiveCallbackGroup()  # a build takes seconds: never in front of rate commands

            def answer(kind: str, text: str, res: Any) -> Any:
                out = self._heads.put(kind, text).result()  # one at a time, on the head thread
                res.success, res.message = out.ok, out.message
                return res

            self.create_service(add, "~/add_head", lambda q, r: answer("add_head", q.config, r), callback_group=group)
            self.create_service(
                remove, "~/remove_head", lambda q, r: answer("remove_head", q.name, r), callback_group=group
            )

        def _services(self, group: Any) -> None:
            core = self.core
            self._head_services()
            found = find_services()
            if found is not None:
                change, names = found

                def on_change(req: Any, res: Any) -> Any:
                    try:
                        core.set_rate(req.model_name, float(req.new_rate))
                        res.success = True
                    except ValueError as e:
                        self.get_logger().warning(f"ChangeModelRate refused: {e}")
                        res.success = False
                    return res

                def on_names(_req: Any, res: Any) -> Any:
                    res.model_names = list(core.model_names)
                    return res

                self.create_service(change, "~/change_model_rate", on_change, callback_group=group)
                self.create_service(names, "~/get_model_names", on_names, callback_group=group)
                return
            from std_srvs.srv import Trigger

            def on_trigger(_req: Any, res: Any) -> Any:
                res.success, res.message = True, json.dumps(core.model_names)
                return res

            self.create_service(Trigger, "~/get_model_names", on_trigger, callback_group=group)
            for m in core.model_names:
                self.declare_parameter(
                    f"rate.{m}",
                    -1.0,
                    ParameterDescriptor(description=f"rate limit of {m} in Hz; 0 pauses; negative: no limit"),
                )

            for h in core.config.heads:
                self.declare_parameter(
                    f"priority.{h.name}",
                    h.priority,
                    ParameterDescriptor(
                        description=f"priority of {h.name}, {checks.MIN_PRIORITY} to {checks.MAX_PRIORITY}; "
                        "higher: more important"
                    ),
                )

            def on_params(params: list[Any]) -> Any:
                for prm in params:
                    kind, _, key = prm.name.partition(".")
                    try:
                        if kind == "rate":
                            core.set_rate(key, float(prm.value))
                        elif kind == "priority":
                            core.set_priority(key, prm.value)
                    except (ValueError, TypeError) as e:
                        return SetParametersResult(successful=False, reason=str(e))
                return SetParametersResult(successful=True)

            self.add_on_set_parameters_callback(on_params)

        def _wait_commands(self, timeout: float) -> list[tuple[str, str, str]]:
            try:
                got = [self._commands.get(timeout=timeout)]
            except queue.Empty:
                return []
            while not self._commands.empty():
                got.append(self._commands.get_nowait())
            return got

        def _output_loop(self) -> None:
            while not self._stop.is_set():
                for topic, payload in self.core.poll_outputs(timeout=0.05):
                    msg = ros_image(payload) if isinstance(payload, ImageOut) else ros_detections(payload)
                    with self._writing:
                        pub = self._pubs.get(topic.topic)
                        if pub is None:  # its head was removed meanwhile (Note [Head commands])
                            continue
                        pub.publish(msg)
                    self.core.count_published(topic)

        def shutdown(self) -> None:
            self._stop.set()
            for th in self._threads:
                th.join(timeout=5.0)
            self.core.stop()

    def _detection_type() -> Any:
        try:
            from vision_msgs.msg import Detection2DArray
        except ImportError:
            raise RuntimeError(
                "a detection head needs vision_msgs (>= 4.0), e.g. apt install ros-$ROS_DISTRO-vision-msgs"
            ) from None
        return Detection2DArray

    return VpengineNode()


def main(argv: list[str] | None = None) -> int:
    """``python -m vpengine.ros2.node --ros-args -p config:=FILE -p input_topic:=/camera/image_raw``."""
    rclpy = _require_rclpy()
    from rclpy.executors import MultiThreadedExecutor

    rclpy.init(args=argv if argv is not None else sys.argv)
    node = build_node()
    executor = MultiThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except KeyboardInterrupt:
        pass
    finally:
        node.shutdown()
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
