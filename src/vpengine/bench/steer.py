"""Priorities under overload, and how soon a priority change takes effect (Note [Give way] in runtime/governor.py).

One engine on the config's models (``configs/bench.yaml`` by default: DINOv2 ViT-S/14 + depth, segmentation and
detection at 1080p; ``--set`` as everywhere), ``--cameras`` cameras (8, at least 2) each at ``--fps`` (30 Hz),
their frames submitted together as synchronised cameras deliver them (a tick the feeder could not keep is skipped
and counted, never made up for in a burst), more than the device serves. Three phases:

* ``equal``: every priority equal (the default), ``--seconds`` long. Per lane (head, camera), as the engine counted
  it (``stats()``, ``Engine.recent_runs``): runs per second, runs skipped by reason (rate, priority, overload),
  deadline misses, the throttle cap and the end-to-end latency of every run (p50, p99); as the stream took its
  outputs: their rate and latency from submit to the host (p50, p99), by when
  each was published, so a stream that took them late (a thousand mapped outputs a second on one thread) does not
  count its own lag. Per head: the outputs the stream missed.
* ``priority``: ``--head`` on the first camera raised to ``--priority`` (``Engine.set_priority``), measured the same
  way after ``--settle`` s: that lane should hold the cameras' rate within its deadline while the others give way.
* ``change``: through each door of ``--doors`` (``api``: ``Engine.set_priority``; ``web``: the live view's
  ``PUT /api/priority/<head>@<camera>``; ``ros2``: a diagnostic_msgs/KeyValue on ``<ns>/set_priority`` through
  CycloneDDS from a second participant of this process, taken by the ROS 2 interface's own control path),
  ``--changes`` times: the config's last head on the last camera is put below every lane (``MIN_PRIORITY``), so the
  governor throttles it first, and once it runs at most at a third of the cameras' rate (or after ``--settle`` s)
  it is raised above every lane. Per change: when the command reached the engine (``applied_ms``) and when the
  lane's first output of a frame submitted after the call was published (``first_run_ms``, the first run under the
  new order), both from the call; the lane's cap before, and its priority after (the command arrived).

A door that fails (no live view without prometheus-client, no ROS 2 without cyclonedds) is recorded with its error
and the others go on. ::

    vpengine bench steer -c configs/tiny.yaml --set device=cpu --cameras 2 --seconds 3   # anywhere
    vpengine bench steer                                                                   # a GPU machine
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import http.client
import json
import math
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from vpengine import checks
from vpengine.arguments import add_overrides_argument

DOORS = ("api", "web", "ros2")
WAIT_S = 10.0  # the longest wait for a change's first run


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", "-c", default="bench", help="engine config (default: the shipped bench config)")
    add_overrides_argument(p, "mode=thread")
    p.add_argument("--cameras", type=int, default=8, help="cameras, at least 2 (default 8)")
    p.add_argument("--fps", type=float, default=30.0, help="each camera's rate (default 30 Hz)")
    p.add_argument("--seconds", type=float, default=10.0, help="length of the equal and priority phases (default 10)")
    p.add_argument("--settle", type=float, default=3.0, help="seconds for the governor after a change (default 3)")
    p.add_argument("--head", default=None, help="the head raised on the first camera (default: the config's first)")
    p.add_argument("--priority", type=int, default=10, help="its priority (default 10; the others keep 0)")
    p.add_argument("--doors", default=",".join(DOORS), help=f"doors of the change phase (default {','.join(DOORS)})")
    p.add_argument("--changes", type=int, default=5, help="priority changes through each door (default 5)")
    p.add_argument("--name", default=None, help="results file name (default: steer_<device>)")


class _Stream:
    """Synchronised cameras at ``fps`` from a thread of their own, and every result taken on another, kept per lane
    as (published, latency). A thread that fails stops the stream; ``check`` raises its error."""

    def __init__(self, eng: Any, imgs: list[np.ndarray], fps: float) -> None:
        self.eng, self.imgs, self.fps = eng, imgs, fps
        self.lanes: dict[tuple[str, str], list[tuple[float, float]]] = collections.defaultdict(list)
        self.submitted: dict[int, float] = {}  # frame id -> when its submit began
        self.ticks_missed = 0
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._error: BaseException | None = None
        eng.results()  # the stream starts now
        self._threads = [threading.Thread(target=self._guard, args=(f,), daemon=True) for f in (self._feed, self._take)]
        for t in self._threads:
            t.start()

    def _guard(self, loop: Callable[[], None]) -> None:
        try:
            loop()
        except BaseException as e:
            self._error = self._error or e
            self._stop.set()

    def check(self) -> None:
        if self._error is not None:
            raise RuntimeError(f"the stream stopped: {type(self._error).__name__}: {self._error}") from self._error

    def _feed(self) -> None:
        t0, k = time.monotonic(), 0
        while not self._stop.is_set():
            behind = int((time.monotonic() - t0) * self.fps) - k
            if behind > 0:  # ticks it could not keep: skipped, as a camera's frames would be, not sent in a burst
                self.ticks_missed += behind
                k += behind
            delay = t0 + k / self.fps - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                return
            stamp = time.time()
            for i, cam in enumerate(self.eng.cameras):
                with self.lock:  # the id and its time together: a reader never sees one without the other
                    sent = time.monotonic()  # before submit: a frame whose submit began before a call is not after it
                    fid = self.eng.submit(self.imgs[(k + i) % len(self.imgs)], timestamp=stamp, camera=cam)
                    self.submitted[fid] = sent
            k += 1

    def _take(self) -> None:
        while not self._stop.is_set():
            for r in self.eng.results(timeout=0.05, copy=False):
                self.lanes[(r.head, r.camera)].append((r.t_publish, r.latency))

    def first_run(self, head: str, camera: str, since: float, timeout: float) -> float | None:
        """When the first output of (head, camera) for a frame submitted at ``since`` or later was published (None:
        not within ``timeout``). Read from the engine's newest output, not the stream, which may lag behind."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.check()
            r = self.eng.latest(head, copy=False, camera=camera)
            if r is not None:
                with self.lock:
                    sent = self.submitted.get(r.frame_id, 0.0)
                if sent >= since:
                    return float(r.t_publish)
            time.sleep(0.001)
        return None

    def window(self, t0: float, t1: float) -> dict[tuple[str, str], dict[str, Any]]:
        from vpengine.bench.paper.harness import pct

        out = {}
        for lane, rec in list(self.lanes.items()):
            lat = [latency for at, latency in rec if t0 <= at < t1]
            out[lane] = {"achieved_hz": len(lat) / (t1 - t0), "latency_ms": pct(lat) if lat else None}
        return out

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=10)


def _lanes(stats: dict[str, Any], heads: Any) -> dict[tuple[str, str], dict[str, Any]]:
    keys = ("runs", "skipped_by", "deadline_misses", "priority", "cap_hz")
    return {
        (head, cam): {k: s[k] for k in keys}
        for cam, models in stats["cameras"].items()
        for head, s in models.items()
        if head in heads
    }


def _phase(eng: Any, seconds: float) -> tuple[dict[str, Any], tuple[float, float]]:
    """Each lane over ``seconds`` from now as the engine counted it (runs, skips, deadline misses, and the
    end-to-end latency of every run that started in the span, as the engine recorded it: whole whether or not the
    stream keeps up), and the span: what the stream took of the outputs is added later (:func:`_seen`), once it has
    caught up with them."""
    from vpengine.bench.paper.harness import pct

    s0, t0 = eng.stats(), time.monotonic()
    time.sleep(seconds)
    s1, t1 = eng.stats(), time.monotonic()
    before, after = _lanes(s0, eng.plan.heads), _lanes(s1, eng.plan.heads)
    lanes = []
    for (head, cam), a in after.items():
        b = before.get((head, cam), a)
        row = {"head": head, "camera": cam, "priority": a["priority"], "cap_hz": a["cap_hz"]}
        row |= {"runs_hz": (a["runs"] - b["runs"]) / (t1 - t0)}
        row |= {"skipped_by": {k: v - b["skipped_by"][k] for k, v in a["skipped_by"].items()}}
        row |= {"deadline_misses": a["deadline_misses"] - b["deadline_misses"]}
        starts, e2e = eng.recent_runs(head, cam)
        in_span = e2e[(starts >= t0) & (starts < t1)]
        # the engine keeps a lane's last 512 runs: whole if it still holds one from before the span
        row |= {"engine_latency_ms": pct(in_span) if len(in_span) else None}
        row |= {"engine_latency_whole": bool(len(starts) and starts[0] < t0)}
        lanes.append(row)
    missed = {h: r["missed"] - s0["results"].get(h, {}).get("missed", 0) for h, r in s1["results"].items()}
    return {"lanes": lanes, "results_missed": missed}, (t0, t1)


def _seen(phase: dict[str, Any], stream: _Stream, span: tuple[float, float]) -> None:
    """Add what the stream took of each lane's outputs published within ``span``."""
    seen = stream.window(*span)
    for row in phase["lanes"]:
        row |= seen.get((row["head"], row["camera"]), {"achieved_hz": 0.0, "latency_ms": None})


def _summary(phase: dict[str, Any], head: str, camera: str) -> str:
    rows = phase["lanes"]
    lane = next(r for r in rows if (r["head"], r["camera"]) == (head, camera))
    others = [r for r in rows if r is not lane]
    held_back = sum(sum(r["skipped_by"].values()) for r in others)
    return (
        f"{head}@{camera} {lane['runs_hz']:.1f} Hz, {lane['deadline_misses']} deadline misses, p99 "
        f"{(lane['engine_latency_ms'] or {}).get('p99', math.nan):.1f} ms; the other lanes "
        f"{np.mean([r['runs_hz'] for r in others]):.1f} Hz on average, {held_back} runs skipped"
    )


# ------------------------------------------------------------------------------------------------- doors
@contextlib.contextmanager
def _door(name: str, eng: Any, applied: list[float]) -> Iterator[Callable[[str, str, int], None]]:
    """A function that sets the priority of (head, camera) through door ``name``, for as long as the block runs;
    each time a command reaches the engine, its time goes into ``applied``."""
    if name == "api":

        def call(head: str, cam: str, p: int) -> None:
            eng.set_priority(head, p, camera=cam)
            applied.append(time.monotonic())

        yield call
    elif name == "web":
        from vpengine.web.server import WebServer

        with WebServer(eng) as view:
            conn = http.client.HTTPConnection("127.0.0.1", view.port, timeout=10)

            def put(head: str, cam: str, p: int) -> None:
                conn.request("PUT", f"/api/priority/{head}@{cam}", json.dumps({"priority": p}).encode())
                resp = conn.getresponse()
                body = resp.read()
                if resp.status != 200:
                    raise RuntimeError(f"PUT /api/priority/{head}@{cam}: {resp.status} {body!r}")
                applied.append(time.monotonic())  # the server answers once the engine has it

            try:
                yield put
            finally:
                conn.close()
    else:
        yield from _ros2_door(eng, applied)


def _ros2_door(eng: Any, applied: list[float]) -> Iterator[Callable[[str, str, int], None]]:
    """The ROS 2 interface's control path (its DDS reader of ``<ns>/set_priority``, the control loop, Ros2Core's
    parsing) on this engine, and a ROS 2 user's writer on a second participant of this process (CycloneDDS may
    deliver between them without the network: a user on another machine adds its link). Only the control path:
    the bench, not the interface, feeds frames and takes results."""
    import os

    from vpengine.ros2 import dds_types as T
    from vpengine.ros2.control import ControlLoop
    from vpengine.ros2.core import Ros2Core
    from vpengine.ros2.dds import DdsContext, bridge_config, loopback_config

    core = Ros2Core(eng.config, cameras=eng.cameras)
    core.engine = eng  # started here; the interface would start its own
    apply = core.set_priority

    def set_priority(key: str, value: str | int) -> tuple[str, int]:
        out = apply(key, value)
        applied.append(time.monotonic())
        return out

    core.set_priority = set_priority  # type: ignore[method-assign]
    domain = 100 + os.getpid() % 100  # a domain of its own: another run on the machine must not steer this one
    stop = threading.Event()
    failed: list[BaseException] = []
    ours = user = thread = None
    try:
        ours = DdsContext(domain, bridge_config(loopback_config(large_messages=False)))
        user = DdsContext(domain)  # a second participant of the domain ``ours`` configured
        reader = ours.reader(f"{core.namespace}/set_priority", T.KeyValue_, "default")
        writer = user.writer(f"{core.namespace}/set_priority", T.KeyValue_, "default")

        def commands(timeout: float) -> list[tuple[str, str, str]]:
            return [("priority", kv.key, kv.value) for kv in reader.take(16)] if reader.wait(timeout) else []

        def run() -> None:
            try:
                ControlLoop(core, lambda d: None, commands, period_s=1.0).run(stop)
            except BaseException as e:
                failed.append(e)

        thread = threading.Thread(target=run, name="ros2-control", daemon=True)
        thread.start()
        deadline = time.monotonic() + 10
        while writer.matched() < 1 and time.monotonic() < deadline:  # discovery before the first command
            time.sleep(0.05)
        if writer.matched() < 1:
            raise RuntimeError("the ROS 2 door's DDS writer found no reader in 10 s")

        def publish(head: str, cam: str, p: int) -> None:
            if failed:
                raise RuntimeError(f"the ROS 2 control loop stopped: {failed[0]!r}") from failed[0]
            writer.write(T.KeyValue_(f"{head}@{cam}", str(p)))

        yield publish
    finally:
        stop.set()
        if thread is not None:
            thread.join(timeout=5)
        if user is not None:
            user.close()
        if ours is not None and not (thread is not None and thread.is_alive()):  # never under a live reader
            ours.close()


def _throttled(eng: Any, head: str, cam: str, below_hz: float, settle: float) -> float | None:
    """Wait (at most ``settle`` s) until the governor caps (head, cam) at ``below_hz`` or lower; its cap then."""
    deadline = time.monotonic() + settle
    while True:
        cap = eng.stats()["cameras"][cam][head]["cap_hz"]
        if (cap is not None and cap <= below_hz) or time.monotonic() >= deadline:
            return cap
        time.sleep(0.1)


def _change(
    eng: Any, stream: _Stream, door: str, head: str, cam: str, top: int, changes: int, settle: float, fps: float
) -> list[dict[str, Any]]:
    """Per call raising (head, cam) to ``top``: see the module's docstring."""
    from vpengine.bench.paper.harness import log

    out = []
    applied: list[float] = []
    with _door(door, eng, applied) as set_priority:
        for _ in range(changes):
            eng.set_priority(head, checks.MIN_PRIORITY, camera=cam)  # below every lane: throttled first
            cap = _throttled(eng, head, cam, fps / 3, settle)
            applied.clear()
            t0 = time.monotonic()
            set_priority(head, cam, top)
            first = stream.first_run(head, cam, t0, WAIT_S)
            lane = eng.stats()["cameras"][cam][head]
            row = {"applied_ms": (applied[0] - t0) * 1e3 if applied else None, "cap_hz_before": cap}
            row |= {"first_run_ms": None if first is None else (first - t0) * 1e3, "priority_after": lane["priority"]}
            out.append(row)
            if first is None:
                log(f"{door}: {head}@{cam} gave no output of a later frame within {WAIT_S:g} s: {row}")
    eng.set_priority(head, 0, camera=cam)

    def ms(v: float | None) -> str:
        return "-" if v is None else f"{v:.0f}"

    log(
        f"change through {door}: first run " + ", ".join(ms(c["first_run_ms"]) for c in out) + " ms after the call "
        "(applied after "
        + ", ".join(ms(c["applied_ms"]) for c in out)
        + " ms; caps before "
        + ", ".join("-" if c["cap_hz_before"] is None else f"{c['cap_hz_before']:.1f}" for c in out)
        + " Hz)"
    )
    return out


def _config(base: Any, cameras: int) -> Any:
    from vpengine.config import load_config

    return load_config(base.model_dump() | {"cameras": [{"name": f"cam{i}"} for i in range(cameras)]})


def _check(args: argparse.Namespace) -> list[str]:
    """The doors asked for; ValueError naming any bad argument, before an engine starts."""
    if args.cameras < 2:
        raise ValueError(f"--cameras {args.cameras}: at least 2 (a lane raised on the first, one changed on the last)")
    for name in ("fps", "seconds"):
        if not getattr(args, name) > 0:
            raise ValueError(f"--{name} {getattr(args, name)}: must be > 0")
    if args.settle < 0 or args.changes < 0:
        raise ValueError(f"--settle {args.settle}, --changes {args.changes}: must be >= 0")
    if not checks.MIN_PRIORITY < args.priority < checks.MAX_PRIORITY:
        raise ValueError(
            f"--priority {args.priority}: from {checks.MIN_PRIORITY + 1} to {checks.MAX_PRIORITY - 1} (the changed "
            "lane goes one above it and, between changes, to the lowest)"
        )
    doors = [d.strip() for d in args.doors.split(",") if d.strip()]
    unknown = [d for d in doors if d not in DOORS]
    if unknown:
        raise ValueError(f"--doors: {', '.join(unknown)} not known; accepted: {', '.join(DOORS)}")
    return doors


def main(args: argparse.Namespace) -> int:
    from vpengine.bench.common import write_results
    from vpengine.bench.paper.harness import Bench, log
    from vpengine.config import load_config
    from vpengine.engine import Engine

    doors = _check(args)
    cfg = _config(load_config(args.config, list(args.overrides)), args.cameras)
    names = [h.name for h in cfg.heads]
    head = args.head or names[0]
    if head not in names or len(names) < 2:
        raise ValueError(f"--head {head!r}: one of the config's heads {names}, with another to give way")
    raised = names[-1] if names[-1] != head else names[0]
    res: dict[str, Any] = {"config": args.config, "overrides": list(args.overrides), "mode": cfg.mode}
    res |= {"cameras": args.cameras, "fps_per_camera": args.fps, "head": head, "priority": args.priority}
    out_name = args.name or f"steer_{str(cfg.device).split(':')[0]}"
    spans: dict[str, tuple[float, float]] = {}
    with Engine(cfg) as eng:
        first, last = eng.cameras[0], eng.cameras[-1]
        stream = _Stream(eng, Bench(cfg).images(), args.fps)
        try:
            time.sleep(args.settle)
            res["equal"], spans["equal"] = _phase(eng, args.seconds)
            stream.check()
            log("equal priorities: " + _summary(res["equal"], head, first))
            write_results(args.out, out_name, res)  # a run cut short keeps what it measured
            eng.set_priority(head, args.priority, camera=first)
            time.sleep(args.settle)
            res["priority"], spans["priority"] = _phase(eng, args.seconds)
            stream.check()
            log(f"{head}@{first} at priority {args.priority}: " + _summary(res["priority"], head, first))
            write_results(args.out, out_name, res)
            res["change"] = {"lane": f"{raised}@{last}", "priority": args.priority + 1, "doors": {}}
            for door in doors:
                try:
                    done: Any = _change(
                        eng, stream, door, raised, last, args.priority + 1, args.changes, args.settle, args.fps
                    )
                except (ImportError, RuntimeError, OSError) as e:  # this door, not the run
                    stream.check()
                    done = {"error": f"{type(e).__name__}: {e}"}
                    log(f"change through {door}: {done['error']}")
                res["change"]["doors"][door] = done
                write_results(args.out, out_name, res)
        finally:
            res["ticks_missed"] = stream.ticks_missed
            stream.close()
            for phase, span in spans.items():  # the stream has had the time since to take what they published
                _seen(res[phase], stream, span)
    print(write_results(args.out, out_name, res))
    return 0
