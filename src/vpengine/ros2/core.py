"""The engine behind a ROS 2 interface, with no middleware: messages in, neutral outputs out.

The DDS bridge (:mod:`vpengine.ros2.bridge`), the rclpy node (:mod:`vpengine.ros2.node`) and the rosbag2 source and
sink (:mod:`vpengine.io.bag`) build on this and on its parts: :mod:`~vpengine.ros2.messages` (message types,
decoding), :mod:`~vpengine.ros2.outputs` (each head's topics and messages), :mod:`~vpengine.ros2.frames` (the book of
recent frames), :mod:`~vpengine.ros2.control` (rate and priority commands, the control thread),
:mod:`~vpengine.ros2.heads` (heads added and removed at run time) and :mod:`~vpengine.ros2.diagnostics`. None of
them imports a middleware.

Note [Output headers]: every output of a head carries the ``header`` (stamp *and* frame_id) of the input message it
was computed from, never the time of publishing. The engine only knows integer frame ids and a float capture time;
a float cannot hold a ROS stamp exactly (1.7e9 s has a resolution of ~240 ns), so :attr:`Ros2Core.book` keeps the exact
input header per engine frame id, and outputs look their header up by the result's frame id. Only if the book has
already forgotten that frame (more than ``HEADERS_KEPT`` frames in flight, which the engine never has) does the
header fall back to the float capture time, which is still the input's time; that is counted
(``header_fallbacks``).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from vpengine.checks import priority_target
from vpengine.recent_frames import RecentFrames
from vpengine.ros2.control import model_at, parse_priority, parse_rate_command
from vpengine.ros2.diagnostics import (
    OK,
    SILENT_AFTER_S,
    WARN,
    DiagnosticsOut,
    Rejections,
    Status,
    camera_status,
    model_status,
    receive_buffer_advice,
)
from vpengine.ros2.heads import REFUSALS, HeadOutcome, TopicsHook, error_text, named_in, opened_text
from vpengine.ros2.messages import Header, InputError, as_uint8, compressed_to_frame, image_to_frame
from vpengine.ros2.outputs import OutputTopic, Payload, normalize_namespace, payload_for, plan_outputs

if TYPE_CHECKING:
    from vpengine.engine import Engine

log = logging.getLogger("vpengine.ros2")
#: Input headers kept for the outputs still to come (Note [Output headers])
HEADERS_KEPT = 4096


# --------------------------------------------------------------------------------------------------- input
def input_topics(given: Sequence[str]) -> str | dict[str, str]:
    """Input topics as given (``--input-topic``, the node's ``input_topics``) -> the one camera's topic, or camera
    name -> topic (``NAME=TOPIC`` each, several cameras). ValueError for a mix, a camera named twice or several
    unnamed topics."""
    from vpengine.named_inputs import split_camera

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


# ------------------------------------------------------------------------------------------------- the core
class Ros2Core:
    """The engine behind a ROS 2 interface, with no middleware: messages in, neutral outputs out.

    A transport (DDS bridge, rclpy node) feeds input messages to :meth:`handle_image` / :meth:`handle_compressed`
    from its receive thread, publishes what :meth:`poll_outputs` returns from another thread, forwards rate and
    priority commands to :meth:`set_rate` and :meth:`set_priority`, and publishes :meth:`diagnostics` about once a
    second. Uses the public Engine API only (submit, results, set_rate, set_priority, add_head, remove_head, stats,
    head_info).

    Frames of any size go to the engine as they come, and every output is published at the camera's size, in its
    pixels, under its header (Note [Frame grid] in engine/boundary.py). ``input_size="config"`` starts the engine at once
    with the config's ``input.height/width``; ``"first"`` starts it when the first message arrives, with the models
    at that message's size, so a camera's frames need no resizing (messages arriving during start-up are not seen).

    Several cameras (``cameras``: their names, one input topic each; or a config with ``cameras``): every message
    is handed in with its camera (``handle_image(msg, camera)``, from one thread per topic if need be), and each
    camera's outputs go out under its own namespace, ``<ns>/<camera>/<head>/...``, with that camera's input header.
    Rate and priority commands may name ``head@camera``; /diagnostics has a status per camera.

    ``keep_frames`` keeps recent input frames in :attr:`book` for a viewer that draws on them (the web view), as
    ``seg_overlay`` does for its overlays.
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
        keep_frames: bool = False,
    ) -> None:
        from vpengine.named_inputs import config_for_cameras

        if input_size not in ("config", "first"):
            raise ValueError(f"input_size must be 'config' or 'first', got {input_size!r}")
        # images on a topic decode to uint8 frames: the config's input.dtype is for the API's callers (as in the CLI)
        self.config = config_for_cameras(
            config, list(cameras) if cameras else None, [*overrides, "input.dtype=uint8"], "input topics"
        )
        self.namespace = normalize_namespace(namespace)
        self.input_size = input_size
        planner = self._new_engine(self.config)  # planned only: head metadata without starting anything
        self.model_names: list[str] = self.config.model_names()
        #: the engine's cameras, in priority order; with several, each has its own input topic and namespace
        self.cameras: list[str] = planner.cameras
        self.several = len(self.cameras) > 1
        self._depth_color, self._seg_overlay = depth_color, seg_overlay
        infos = {h.name: planner.head_info(h.name) for h in self.config.heads}
        topics, unmapped = self._plan(infos, planner)
        for h in unmapped:
            log.warning("head %r has no ROS 2 message mapping (kind 'generic'); its outputs are not published", h)
        self._route(infos, topics)
        # add_head / remove_head change the heads and their topics one command at a time (Note [Head commands])
        self._heads_lock = threading.Lock()
        self.last_head_outcome: HeadOutcome | None = None
        self.book = RecentFrames[Header](
            frames=16 * len(self.cameras) if seg_overlay or keep_frames else 0, tags=HEADERS_KEPT
        )
        self._next_fid = 0  # engine frame ids are ours, so a header is booked before its frame is submitted
        self.engine: Engine | None = None
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
        #: input messages and outputs that could not be used, per reason (Note [Rejection log] in
        #: :mod:`vpengine.ros2.diagnostics`)
        self.rejected = Rejections("input message rejected")
        self.output_errors = Rejections("output not published")
        self.outputs_superseded: collections.Counter[str] = collections.Counter()
        # Note [Input link] (in vpengine.ros2.diagnostics): when a publisher of the input topic was matched (None:
        # none is), the transport's receive-buffer advice, and the largest input message seen (bytes)
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

    def _plan(self, infos: dict[str, dict[str, Any]], engine: Engine) -> tuple[list[OutputTopic], list[str]]:
        """The output topics of the heads ``infos`` (head -> its info), each on the cameras it serves in ``engine``,
        and the heads with no ROS message mapping (:func:`plan_outputs`)."""
        served = {c: [h for h in infos if c in engine.lanes.served(h)] for c in self.cameras}
        return plan_outputs(
            infos, self.namespace, self._depth_color, self._seg_overlay, served if self.several else None
        )

    def _route(self, infos: dict[str, dict[str, Any]], topics: list[OutputTopic]) -> None:
        """Publish each head's outputs on ``topics`` from now on. The output thread reads the routes once per
        result, so a head command swaps them whole (one assignment), never edits them in place."""
        routes: dict[tuple[str | None, str], tuple[list[OutputTopic], dict[str, Any]]] = {}
        for t in topics:
            routes.setdefault((t.camera, t.head), ([], infos[t.head]))[0].append(t)
        self.head_infos: dict[str, dict[str, Any]] = infos
        self.topics: list[OutputTopic] = topics
        self._routes = routes

    def _new_engine(self, cfg: Any) -> Engine:
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
        # outside the lock: each camera's input thread fills its own slot, at once with the others' (Note [Frames of
        # several cameras at once] in engine/core.py)
        t0 = time.thread_time()
        try:
            eng.submit(frame, frame_id=fid, timestamp=header.seconds, camera=camera)
        except ValueError as e:
            error: ValueError | None = e
        else:
            error = None
            with self._input_lock:
                self.busy["submit"] += time.thread_time() - t0
        if error is not None:
            self._reject("engine", str(error), camera)
            return None
        self._count("submitted", camera)
        return fid

    # -------------------------------------------------------------------------------------------- output
    def poll_outputs(self, timeout: float = 0.1) -> list[tuple[OutputTopic, Payload]]:
        """The head outputs since the last call as (topic, message), oldest first; waits up to ``timeout``.

        Note [Output QoS] (in :mod:`vpengine.ros2.outputs`): when the engine takes the newest frame (``input_mode:
        latest``), only each head's newest result is converted and published; older ones that waited for the output
        thread (it was writing) are counted in ``outputs_superseded.<head>``. Publishing them would only put stale
        images in front of the fresh one. With ``input_mode: fifo`` every result goes out, in order."""
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
            route = self._routes.get((r.camera if self.several else None, r.head))
            if route is None:  # a head with no ROS mapping, or one added or removed just now
                continue
            topics, info = route
            header = self.book.tag(r.frame_id)
            if header is None:  # see Note [Output headers]
                self.counters["header_fallbacks"] += 1
                header = Header.from_seconds(r.capture_time)
            frame = self.book.frame(r.frame_id)
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
    @contextlib.contextmanager
    def _command(self, kind: str) -> Iterator[None]:
        """Counts a ``kind`` command (rate, priority) as applied, ``<kind>_commands``, or as rejected,
        ``<kind>_commands_rejected``: then a ValueError naming what is wrong (a KeyError's text without quotes)."""
        try:
            yield
        except (ValueError, KeyError) as e:
            self.counters[f"{kind}_commands_rejected"] += 1
            raise ValueError(str(e.args[0]) if isinstance(e, KeyError) and e.args else str(e)) from None
        self.counters[f"{kind}_commands"] += 1

    def _started(self) -> Engine:
        if self.engine is None:
            raise ValueError("the engine has not started yet (it starts on the first input message)")
        return self.engine

    def set_rate(self, key: str, value: str | float | None) -> tuple[str, float | None]:
        """Apply a rate command: ``key`` a model name, or ``model@camera`` for one camera's rate; ``value`` the rate
        as text (the set_rate topic) or as a number (services, parameters), see :func:`parse_rate_command`. Raises
        ValueError naming what is wrong; counted."""
        with self._command("rate"):
            key, hz = parse_rate_command(key, value, self.model_names, self.cameras)
            model, camera = model_at(key, self.model_names, self.cameras)
            self._started().set_rate(model, hz, camera=camera)
        log.info("rate of %s set to %s", key, "unlimited" if hz is None else f"{hz:g} Hz")
        return key, hz

    def set_priority(self, key: str, value: str | int) -> tuple[str, int]:
        """Apply a priority command: ``key`` a head, ``head@camera`` for one camera's lane or ``@camera`` for the
        camera's own priority (:func:`vpengine.checks.priority_target`); ``value`` an integer from
        checks.MIN_PRIORITY to MAX_PRIORITY, as text (the set_priority topic) or a number (parameters), see
        :func:`parse_priority`. Raises ValueError naming what is wrong, and then nothing changes
        (``Engine.set_priority``); counted."""
        key = str(key).strip()
        with self._command("priority"):
            priority = parse_priority(value)
            head, camera = priority_target(key)
            self._started().set_priority(head, priority, camera=camera)
        log.info("priority of %s set to %d", key, priority)
        return key, priority

    def add_head(self, config_text: str, open_topics: TopicsHook) -> HeadOutcome:
        """Add a head while the engine runs: ``config_text`` is its config as under ``heads:`` (YAML or JSON),
        validated like the config file (``Engine.add_head``). Its output topics, per camera it serves, are planned
        like the others' and handed to ``open_topics`` (the transport creates their publishers) before its outputs
        are routed to them. The outcome names the engine's error (a bad config, a name taken, no seat free, a failed
        build) or a clash of ROS names, and then nothing changed. Takes seconds (build and warm-up): call it on no
        thread that must answer meanwhile (Note [Head commands] in :mod:`vpengine.ros2.heads`). Counted."""
        with self._heads_lock:
            name = named_in(config_text)
            try:
                eng = self._started()
                name = eng.add_head(config_text)
                try:
                    infos = {**self.head_infos, name: eng.head_info(name)}
                    topics, _ = self._plan(infos, eng)
                    added = [t for t in topics if t.head == name]
                    open_topics(added)
                except BaseException:
                    eng.remove_head(name)  # a ROS name taken, or no publisher: the engine as it was
                    raise
            except REFUSALS as e:
                return self._head_outcome("add_head", name, e)
            self._route(infos, topics)
            self.model_names = eng.config.model_names()
            names = tuple(t.topic for t in added)
            return self._head_outcome("add_head", name, opened_text(name, names), names)

    def remove_head(self, name: str, close_topics: TopicsHook) -> HeadOutcome:
        """Remove head ``name`` while the engine runs (``Engine.remove_head``): its outputs stop being routed, then
        ``close_topics`` gets its topics (the transport closes their publishers). The outcome names the engine's
        error (an unknown head, the foundation model, the last head), and then nothing changed. Counted."""
        name = str(name).strip()
        with self._heads_lock:
            try:
                eng = self._started()
                eng.remove_head(name)
            except REFUSALS as e:
                return self._head_outcome("remove_head", name, e)
            gone = [t for t in self.topics if t.head == name]
            self._route(
                {h: i for h, i in self.head_infos.items() if h != name}, [t for t in self.topics if t not in gone]
            )
            self.model_names = eng.config.model_names()
            close_topics(gone)
            names = tuple(t.topic for t in gone)
            return self._head_outcome("remove_head", name, f"head {name!r} removed", names)

    def _head_outcome(
        self, command: str, head: str | None, what: str | BaseException, topics: tuple[str, ...] = ()
    ) -> HeadOutcome:
        ok, message = (False, error_text(what)) if isinstance(what, BaseException) else (True, what)
        self.counters["head_commands" if ok else "head_commands_rejected"] += 1
        out = HeadOutcome(command, head, ok, message, topics, tuple(self.model_names))
        self.last_head_outcome = out
        return out

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
                "priority_commands",
                "priority_commands_rejected",
                "head_commands",
                "head_commands_rejected",
            )
        ]
        if self.last_head_outcome is not None:
            o = self.last_head_outcome
            values.append(("last_head_command", f"{o.command} {o.head}: {'ok' if o.ok else 'refused'}: {o.message}"))
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
            models_here = per_camera.get(camera, {})
            status.append(camera_status(camera, counts, models_here, self.status_prefix, self.hardware_id))
        return DiagnosticsOut(header, status)
