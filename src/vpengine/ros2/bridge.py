"""The DDS bridge: the engine on a ROS 2 graph through CycloneDDS, with no ROS 2 installation.

Topics (``<ns>`` is the namespace, ``/vpengine`` by default; every type is the ROS 2 one, on the wire as ROS 2 sends
it, see :mod:`vpengine.ros2.dds` and :mod:`vpengine.ros2.dds_types`):

==================================  =================================  =========================================
topic                               type                               QoS
==================================  =================================  =========================================
input topic (``--input-topic``)     sensor_msgs/Image                  sensor data (best effort, keep last 5) or
                                    (CompressedImage with              default (reliable, keep last 10)
                                    ``--compressed``, on
                                    ``<input>/compressed``)
``<ns>/<head>/depth``               sensor_msgs/Image 32FC1            latest (reliable, keep last 1; or
                                                                       ``--output-qos default``)
``<ns>/<head>/depth_color``         sensor_msgs/Image bgr8             latest (``--depth-color``)
``<ns>/<head>/classes``             sensor_msgs/Image mono8            latest
``<ns>/<head>/overlay``             sensor_msgs/Image bgr8             latest (``--seg-overlay``)
``<ns>/<head>/detections``          vision_msgs/Detection2DArray       latest
``<ns>/set_rate``                   diagnostic_msgs/KeyValue (in)      default
``<ns>/set_priority``               diagnostic_msgs/KeyValue (in)      default
``<ns>/add_head``                   std_msgs/String (in): the head's   default
                                    config, YAML or JSON
``<ns>/remove_head``                std_msgs/String (in): a head name  default
``<ns>/head_events``                std_msgs/String (JSON): each head  latched
                                    command's outcome
``<ns>/model_names``                std_msgs/String (JSON list)        latched (transient local, keep last 1)
``/diagnostics``                    diagnostic_msgs/DiagnosticArray    default, 1 Hz
==================================  =================================  =========================================

Several cameras (``--input-topic NAME=TOPIC`` for each; ``BridgeOptions.input_topic`` camera -> topic): each
camera's outputs are under ``<ns>/<camera>/<head>/...`` with that camera's input headers, and each input topic has
a thread of its own. Rate and priority commands may name ``head@camera``; an added head gets topics on every camera
it serves.

Change a rate from any ROS 2 machine: ``ros2 topic pub --once /vpengine/set_rate diagnostic_msgs/msg/KeyValue
"{key: depth, value: '5'}"`` (``'0'`` pauses, ``'max'`` removes the limit). Change a priority (an integer from
checks.MIN_PRIORITY to MAX_PRIORITY, higher more important; Note [Give way] in runtime/governor.py) the same way on
``/vpengine/set_priority``: ``{key: depth, value: '10'}``; the key ``depth@front`` is that head's lane of camera
``front`` only, ``@front`` the camera's own priority.

Add a head while it runs: ``ros2 topic pub --once /vpengine/add_head std_msgs/msg/String "{data: '{name: det2,
model: tiny_det}'}"`` (the head's config as under ``heads:`` in a config file, validated like it); once it is built
and warm, its topics are published like the others' and ``<ns>/model_names`` names it. Remove one with ``{data:
det2}`` on ``/vpengine/remove_head``. Each command's outcome, success or the engine's error, is a JSON message on
``<ns>/head_events`` (:class:`vpengine.ros2.heads.HeadOutcome`), also logged and counted in /diagnostics.

Four threads (one more per extra camera): one takes input samples (raw CDR, decoded to a numpy view, handed to
``Engine.submit``), one publishes the results (``Engine.results``; each head's newest, Note [Output QoS] in
:mod:`vpengine.ros2.outputs`), one applies rate and priority commands and publishes diagnostics
(Note [Control path] in :mod:`vpengine.ros2.control`), so neither waits behind the writes of big images, and one
adds and removes heads (Note [Head commands] in :mod:`vpengine.ros2.heads`), so no command waits for a build. All
decisions about content live in :class:`vpengine.ros2.core.Ros2Core` and its parts.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from vpengine.engine import EngineDeadError
from vpengine.ros2 import cdr
from vpengine.ros2 import dds_types as T
from vpengine.ros2.control import ControlLoop, model_names_text
from vpengine.ros2.core import Ros2Core
from vpengine.ros2.dds import DdsContext, Reader, Writer, bridge_config, dds_topic, receive_buffer_granted
from vpengine.ros2.diagnostics import DiagnosticsOut, receive_buffer_limit
from vpengine.ros2.heads import HEAD_COMMANDS, HeadCommands, HeadOutcome
from vpengine.ros2.messages import DETECTIONS_TYPE, DetectionsOut, Header, ImageOut
from vpengine.ros2.outputs import OUTPUT_QOS, OutputTopic

log = logging.getLogger("vpengine.ros2.bridge")


@dataclass
class BridgeOptions:
    """Where the bridge listens and publishes."""

    #: The camera topic, e.g. /camera/image_raw; with several cameras, camera name -> its topic (each camera's
    #: outputs then go under ``<ns>/<camera>/``).
    input_topic: str | Mapping[str, str]
    #: Read sensor_msgs/CompressedImage (jpeg/png) from ``<input_topic>/compressed`` (image_transport's name; a
    #: topic already ending in /compressed is used as is).
    compressed: bool = False
    #: QoS of the input subscription: "sensor" (best effort, keep last 5: what camera drivers publish) or "default"
    #: (reliable, keep last 10; matches only reliable publishers).
    input_qos: Literal["sensor", "default"] = "sensor"
    #: QoS of the output topics: "latest" (reliable, keep last 1) or "default" (ROS 2's, reliable, keep last 10);
    #: see Note [Output QoS] in vpengine.ros2.outputs.
    output_qos: Literal["latest", "default"] = "latest"
    domain_id: int = 0
    #: CycloneDDS XML configuration used instead of $CYCLONEDDS_URI (e.g. ``loopback_config()``); see
    #: :func:`vpengine.ros2.dds.bridge_config` for what the bridge sets itself.
    dds_config: str | None = None
    diagnostics_topic: str = "/diagnostics"
    diagnostics_period_s: float = 1.0

    @property
    def inputs(self) -> dict[str | None, str]:
        """Camera (None: the one camera) -> the topic subscribed for it."""
        topics = {None: self.input_topic} if isinstance(self.input_topic, str) else dict(self.input_topic)
        return {c: self._subscribed(t) for c, t in topics.items()}

    @property
    def subscribed_topic(self) -> str:
        """The topic subscribed (several cameras: ``camera=topic`` each, comma separated)."""
        inputs = self.inputs
        return ", ".join(t if c is None else f"{c}={t}" for c, t in inputs.items())

    def _subscribed(self, topic: str) -> str:
        if self.compressed and not topic.rstrip("/").endswith("/compressed"):
            return topic.rstrip("/") + "/compressed"
        return topic


def _header(h: Header) -> T.Header_:
    return T.Header_(T.Time_(h.sec, h.nanosec), h.frame_id)


def detections_to_dds(d: DetectionsOut) -> T.Detection2DArray_:
    header = _header(d.header)
    return T.Detection2DArray_(
        header,
        [
            T.Detection2D_(
                header,
                [T.ObjectHypothesisWithPose_(T.ObjectHypothesis_(det.class_id, det.score))],
                T.BoundingBox2D_(T.Pose2D_(T.Point2D_(det.center_x, det.center_y), 0.0), det.size_x, det.size_y),
                "",
            )
            for det in d.detections
        ],
    )


def diagnostics_to_dds(d: DiagnosticsOut) -> T.DiagnosticArray_:
    return T.DiagnosticArray_(
        _header(d.header),
        [
            T.DiagnosticStatus_(s.level, s.name, s.message, s.hardware_id, [T.KeyValue_(k, v) for k, v in s.values])
            for s in d.status
        ],
    )


def frames_to_submit(raws: list[Any], every_frame: bool) -> tuple[list[Any], int]:
    """The queued input samples to submit, oldest first, and how many are superseded: all of them in order when the
    engine takes every frame (``every_frame``), else only the newest."""
    if every_frame or len(raws) <= 1:
        return raws, 0
    return raws[-1:], len(raws) - 1


class Ros2Bridge:
    """Runs a :class:`Ros2Core` on CycloneDDS. ``start()``, then ``wait()`` / ``stop()``; or use it as a context
    manager. ``error`` holds the first exception of a worker thread (the bridge stops on it)."""

    def __init__(self, core: Ros2Core, options: BridgeOptions) -> None:
        # bad names and domains fail here, before an engine is started
        inputs = options.inputs
        for topic in inputs.values():
            dds_topic(topic)
        dds_topic(options.diagnostics_topic)
        if len(set(inputs.values())) != len(inputs):
            raise ValueError(f"every camera needs an input topic of its own, got {options.subscribed_topic}")
        named = [c for c in inputs if c is not None]
        if (core.several or named) and (sorted(named) != sorted(core.cameras) or len(named) != len(inputs)):
            raise ValueError(
                f"input topics for cameras {named or '(one, unnamed)'} but the engine's cameras are "
                f"{core.cameras}: give one input topic per camera, NAME=TOPIC"
            )
        if not 0 <= options.domain_id <= 232:
            raise ValueError(f"DDS domain id must be 0..232 (the RTPS port mapping), got {options.domain_id}")
        if options.input_qos not in ("sensor", "default"):
            raise ValueError(f"input QoS {options.input_qos!r} is not known; accepted: sensor, default")
        if options.output_qos not in OUTPUT_QOS:
            raise ValueError(f"output QoS {options.output_qos!r} is not known; accepted: {', '.join(OUTPUT_QOS)}")
        self.core = core
        self.opts = options
        self.dds: DdsContext | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._writers: dict[str, Writer] = {}
        # held while writing an output and while closing a removed head's writers (Note [Head commands])
        self._writing = threading.Lock()
        self.error: BaseException | None = None
        self.ns = core.namespace

    # ------------------------------------------------------------------------------------------ lifecycle
    def start(self) -> Ros2Bridge:
        """Start the engine (unless it waits for the first message), then every DDS entity and both threads.

        On any failure everything started so far is stopped again before the error propagates."""
        try:
            return self._start()
        except BaseException:
            self.stop()
            raise

    def _start(self) -> Ros2Bridge:
        self.core.start()
        o = self.opts
        self.dds = ctx = DdsContext(o.domain_id, bridge_config(o.dds_config))
        self._open_topics(self.core.topics)
        self._diag = ctx.writer(o.diagnostics_topic, T.DiagnosticArray_, "default")
        self._names = ctx.writer(f"{self.ns}/model_names", T.String_, "latched")
        self._names.write(T.String_(model_names_text(self.core.model_names)))
        self._head_events = ctx.writer(f"{self.ns}/head_events", T.String_, "latched")
        self._rates: Reader = ctx.reader(f"{self.ns}/set_rate", T.KeyValue_, "default")
        self._priorities: Reader = ctx.reader(f"{self.ns}/set_priority", T.KeyValue_, "default")
        self._head_commands = {kind: ctx.reader(f"{self.ns}/{kind}", T.String_, "default") for kind in HEAD_COMMANDS}
        for r in (self._priorities, *self._head_commands.values()):
            self._rates.also_wake_for(r)  # the control thread waits for every command topic
        in_type = T.CompressedImage_ if o.compressed else T.Image_
        #: camera (None: the one camera) -> its input reader
        self._inputs: dict[str | None, Reader] = {
            camera: ctx.reader(topic, in_type, o.input_qos) for camera, topic in o.inputs.items()
        }
        if not o.compressed:  # a compressed frame is a fraction of the raw one: no buffer advice for it
            self.core.note_receive_buffer(receive_buffer_granted(receive_buffer_limit()))
            self.core.link_warnings()  # logged now, before the "ready" line, not in the middle of it
        heads = HeadCommands(self.core, self._open_topics, self._close_topics, self._publish_head_outcome)
        self._control = control = ControlLoop(
            self.core,
            self._publish_diagnostics,
            self._wait_commands,
            period_s=o.diagnostics_period_s,
            before_diagnostics=lambda: self.core.note_publishers(sum(r.matched() for r in self._inputs.values())),
            heads=heads,
        )
        # one input thread per camera: a camera's decode never holds another camera's frames back
        self._threads = [
            threading.Thread(
                target=self._guard,
                args=(functools.partial(self._input_loop, reader, camera),),
                name="ros2-input" if camera is None else f"ros2-input-{camera}",
                daemon=True,
            )
            for camera, reader in self._inputs.items()
        ]
        self._threads += [
            threading.Thread(target=self._guard, args=(self._output_loop,), name="ros2-output", daemon=True),
            threading.Thread(
                target=self._guard, args=(lambda: control.run(self._stop),), name="ros2-control", daemon=True
            ),
            threading.Thread(target=self._guard, args=(lambda: heads.run(self._stop),), name="ros2-heads", daemon=True),
        ]
        for th in self._threads:
            th.start()
        log.info(
            "bridge up on DDS domain %d: %s %s -> %s",
            o.domain_id,
            "CompressedImage" if o.compressed else "Image",
            o.subscribed_topic,
            ", ".join(t.topic for t in self.core.topics),
        )
        return self

    def _guard(self, loop: Any) -> None:
        try:
            loop()
        except BaseException as e:
            if self.error is None:
                self.error = e
            log.exception("bridge thread %s failed; stopping", threading.current_thread().name)
            self._stop.set()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the bridge stops (stop() or a failed thread); True if it has stopped."""
        return self._stop.wait(timeout)

    def stop(self) -> None:
        """Stop both threads, the engine and every DDS entity. Safe to call twice."""
        self._stop.set()
        for th in self._threads:
            th.join(timeout=5.0)
        self._threads = []
        self.core.stop()
        if self.dds is not None:
            self.dds.close()
            self.dds = None
        self._writers.clear()

    def __enter__(self) -> Ros2Bridge:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ---------------------------------------------------------------------------------------------- loops
    def _input_loop(self, reader: Reader, camera: str | None) -> None:
        compressed = self.opts.compressed
        decode = cdr.decode_compressed_image if compressed else cdr.decode_image
        handle = self.core.handle_compressed if compressed else self.core.handle_image
        # With newest-wins input (input_mode: latest) the engine would take only the newest of several queued frames,
        # so only that one is submitted and the others are counted as superseded (a frame copy saved each). With
        # input_mode: fifo the engine takes every frame in order, so every queued frame is submitted.
        every_frame = self.core.config.foundation_model.input_mode == "fifo"
        while not self._stop.is_set():
            if not reader.wait(0.2):
                continue
            raws, superseded = frames_to_submit(reader.take_raw(64), every_frame)
            if superseded:
                self.core.count_superseded(superseded, camera)
            for raw in raws:
                try:
                    msg = decode(raw)
                except cdr.CdrError as e:
                    self.core.reject_message("malformed", str(e), camera)
                    continue
                handle(msg, camera)

    def _output_loop(self) -> None:
        while not self._stop.is_set():
            try:
                items = self.core.poll_outputs(timeout=0.05)
            except EngineDeadError:
                # the foundation model failed for good: say so on /diagnostics (ERROR) before the bridge stops
                self._publish_diagnostics(self.core.diagnostics())
                raise
            for topic, payload in items:
                self._publish(topic, payload)

    def _wait_commands(self, timeout: float) -> list[tuple[str, str, str]]:
        if not self._rates.wait(timeout):
            return []
        got = [
            (kind, kv.key, kv.value)
            for kind, reader in (("rate", self._rates), ("priority", self._priorities))
            for kv in reader.take(16)
        ]
        return got + [(kind, "", m.data) for kind, reader in self._head_commands.items() for m in reader.take(16)]

    def _publish_diagnostics(self, d: DiagnosticsOut) -> None:
        self._diag.write(diagnostics_to_dds(d))

    def _open_topics(self, topics: list[OutputTopic]) -> None:
        dds = self.dds
        if dds is None:  # a head finished building as the bridge stopped: refused, the engine as it was
            raise RuntimeError("the bridge is stopping")
        for t in topics:
            dtype = T.Detection2DArray_ if t.msgtype == DETECTIONS_TYPE else T.Image_
            self._writers[t.topic] = dds.writer(t.topic, dtype, self.opts.output_qos)

    def _close_topics(self, topics: list[OutputTopic]) -> None:
        with self._writing:  # never under a write in progress (Note [Head commands])
            for t in topics:
                self._writers.pop(t.topic).close()

    def _publish_head_outcome(self, outcome: HeadOutcome) -> None:
        if self.dds is None:  # stopped meanwhile: nobody to tell (the outcome is logged)
            return
        self._head_events.write(T.String_(outcome.text()))
        if outcome.ok:
            self._names.write(T.String_(model_names_text(outcome.model_names)))
        self._control.diagnostics_now()

    def _publish(self, topic: OutputTopic, payload: Any) -> None:
        busy = self.core.busy
        with self._writing:
            w = self._writers.get(topic.topic)
            if w is None:  # its head was removed meanwhile (Note [Head commands])
                return
            t0 = time.thread_time()
            if isinstance(payload, ImageOut):
                data = cdr.encode_image(payload)
                t1 = time.thread_time()
                w.write_raw(data)
            else:
                sample = detections_to_dds(payload)
                t1 = time.thread_time()
                w.write(sample)  # small: the IDL serializer is fine here
        busy["encode"] += t1 - t0
        busy["write"] += time.thread_time() - t1
        self.core.count_published(topic)
