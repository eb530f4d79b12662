"""Priorities under overload, and how soon a priority change takes effect (Note [Give way] in runtime/governor.py).

One engine on the config's models (``configs/bench.yaml`` by default: DINOv2 ViT-S/14 + depth, segmentation and
detection at 1080p; ``--set`` as everywhere), ``--cameras`` cameras (8) each at ``--fps`` (30 Hz), their frames
submitted together as synchronised cameras deliver them, more than the device serves. Three phases:

* ``equal``: every priority equal (the default), ``--seconds`` long: per lane (head, camera), as the engine counted
  it (``stats()``), its runs per second, p99 latency from submit to output, runs skipped by reason (rate, priority,
  overload), deadline misses, throttle cap and results the stream missed; and as the stream took its outputs,
  their rate and latency from submit to the host (p50, p99), by when each was published (taking 1,000 mapped
  outputs a second can lag on one thread; its lag is not theirs).
* ``priority``: ``--head`` on the first camera raised to ``--priority`` (``Engine.set_priority``), measured the same
  way after ``--settle`` s: that lane should hold the cameras' rate within its deadline while the others give way.
* ``change``: through each door of ``--doors`` (``api``: ``Engine.set_priority``; ``web``: the live view's
  ``PUT /api/priority/<head>@<camera>``; ``ros2``: a diagnostic_msgs/KeyValue on ``<ns>/set_priority`` over
  CycloneDDS, taken by the ROS 2 interface's control path), ``--changes`` times: a lane the governor holds at its
  floor (the config's last head on the last camera) is raised above every other; measured is the time from the
  call to the publishing of that lane's first output of a frame submitted after the call (the first run under
  the new order). The
  lane is put back and throttled again before the next change.

::

    vpengine bench steer -c configs/tiny.yaml --set device=cpu --cameras 2 --seconds 3   # anywhere
    vpengine bench steer                                                                   # a GPU machine
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import http.client
import json
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from vpengine.arguments import add_overrides_argument

DOORS = ("api", "web", "ros2")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", "-c", default="bench", help="engine config (default: the shipped bench config)")
    add_overrides_argument(p, "mode=thread")
    p.add_argument("--cameras", type=int, default=8, help="cameras (default 8)")
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
    as (published, latency); ``watch`` reports the first output of a lane for a frame submitted after a moment."""

    def __init__(self, eng: Any, imgs: list[np.ndarray], fps: float) -> None:
        self.eng, self.imgs, self.fps = eng, imgs, fps
        self.lanes: dict[tuple[str, str], list[tuple[float, float]]] = collections.defaultdict(list)
        self._submitted: dict[int, float] = {}  # frame id -> when submitted
        self._lock = threading.Lock()
        self._watch: tuple[str, str, float, list[float], threading.Event] | None = None
        self._stop = threading.Event()
        eng.results()  # the stream starts now
        self._threads = [threading.Thread(target=f, daemon=True) for f in (self._feed, self._collect)]
        for t in self._threads:
            t.start()

    def _feed(self) -> None:
        t0, k = time.monotonic(), 0
        while not self._stop.is_set():
            delay = t0 + k / self.fps - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                return
            stamp = time.time()
            for i, cam in enumerate(self.eng.cameras):
                with self._lock:  # the id and its time together: the collector must never see one without the other
                    fid = self.eng.submit(self.imgs[(k + i) % len(self.imgs)], timestamp=stamp, camera=cam)
                    self._submitted[fid] = time.monotonic()
            k += 1

    def _collect(self) -> None:
        while not self._stop.is_set():
            for r in self.eng.results(timeout=0.05, copy=False):
                self.lanes[(r.head, r.camera)].append((r.t_publish, r.latency))
                w = self._watch
                if w is not None and (r.head, r.camera) == w[:2]:
                    with self._lock:
                        sent = self._submitted.get(r.frame_id, 0.0)
                    if sent >= w[2] and not w[4].is_set():
                        w[3].append(r.t_publish)
                        w[4].set()

    def watch(self, head: str, camera: str, since: float) -> Callable[[float], float | None]:
        """From now, look for the first output of (head, camera) for a frame submitted at ``since`` or later; the
        returned function waits up to its timeout and gives when that output was published (None: not yet)."""
        seen: list[float] = []
        done = threading.Event()
        self._watch = (head, camera, since, seen, done)
        return lambda timeout: seen[0] if done.wait(timeout) else None

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


def _lane_counts(eng: Any) -> dict[tuple[str, str], dict[str, Any]]:
    keys = ("runs", "skipped_by", "deadline_misses", "priority", "cap_hz", "e2e_latency_ms")
    return {
        (head, cam): {k: s[k] for k in keys}
        for cam, models in eng.stats()["cameras"].items()
        for head, s in models.items()
        if head in eng.plan.heads
    }


def _phase(eng: Any, seconds: float) -> tuple[list[dict[str, Any]], tuple[float, float]]:
    """Each lane over ``seconds`` from now as the engine counted it, and the span: the outputs the stream took are
    added later (:func:`_seen`), once it has caught up with them."""
    before = _lane_counts(eng)
    missed = {h: r["missed"] for h, r in eng.stats()["results"].items()}
    t0 = time.monotonic()
    time.sleep(seconds)
    t1 = time.monotonic()
    after = _lane_counts(eng)
    missed = {h: r["missed"] - missed.get(h, 0) for h, r in eng.stats()["results"].items()}
    rows = []
    for (head, cam), a in after.items():
        b = before.get((head, cam), a)
        row = {"head": head, "camera": cam, "priority": a["priority"], "cap_hz": a["cap_hz"]}
        row |= {"runs_hz": (a["runs"] - b["runs"]) / (t1 - t0), "engine_p99_ms": a["e2e_latency_ms"]["p99"]}
        row |= {"skipped_by": {k: v - b["skipped_by"][k] for k, v in a["skipped_by"].items()}}
        row |= {"deadline_misses": a["deadline_misses"] - b["deadline_misses"], "results_missed": missed.get(head)}
        rows.append(row)
    return rows, (t0, t1)


def _seen(rows: list[dict[str, Any]], stream: _Stream, span: tuple[float, float]) -> None:
    """Add what the stream took of each lane's outputs published within ``span``: their rate and their latency
    from submit to the host (Result.latency, so a stream that took them late does not count its own lag)."""
    seen = stream.window(*span)
    for row in rows:
        row |= seen.get((row["head"], row["camera"]), {"achieved_hz": 0.0, "latency_ms": None})


def _summary(rows: list[dict[str, Any]], head: str, camera: str) -> str:
    lane = next(r for r in rows if (r["head"], r["camera"]) == (head, camera))
    others = [r for r in rows if r is not lane]
    held_back = sum(sum(r["skipped_by"].values()) for r in others)
    return (
        f"{head}@{camera} {lane['runs_hz']:.1f} Hz, p99 {lane['engine_p99_ms']:.1f} ms, "
        f"{lane['deadline_misses']} deadline misses; the other lanes {np.mean([r['runs_hz'] for r in others]):.1f} "
        f"Hz on average, {held_back} runs skipped"
    )


# ------------------------------------------------------------------------------------------------- doors
@contextlib.contextmanager
def _door(name: str, eng: Any) -> Iterator[Callable[[str, str, int], None]]:
    """A function that sets the priority of (head, camera) through door ``name``, for as long as the block runs."""
    if name == "api":
        yield lambda head, cam, p: eng.set_priority(head, p, camera=cam)
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

            try:
                yield put
            finally:
                conn.close()
    elif name == "ros2":
        yield from _ros2_door(eng)
    else:
        raise ValueError(f"--doors: {name!r} is not a door; accepted: {', '.join(DOORS)}")


def _ros2_door(eng: Any) -> Iterator[Callable[[str, str, int], None]]:
    """The ROS 2 interface's control path (its DDS reader of ``<ns>/set_priority``, the control loop, Ros2Core's
    parsing) on this engine, and a ROS 2 user's writer on a participant of its own. Only the control path: the
    bench, not the interface, feeds frames and takes results."""
    import os

    from vpengine.bench.paper.harness import log
    from vpengine.ros2 import dds_types as T
    from vpengine.ros2.control import ControlLoop
    from vpengine.ros2.core import Ros2Core
    from vpengine.ros2.dds import DdsContext, bridge_config, loopback_config

    core = Ros2Core(eng.config, cameras=eng.cameras if len(eng.cameras) > 1 else None)
    core.engine = eng
    applied = core.set_priority

    def set_priority(key: str, value: str | int) -> tuple[str, int]:  # the moment the command reaches the engine
        out = applied(key, value)
        log(f"ros2: {key} = {value} applied at {time.monotonic():.3f}")
        return out

    core.set_priority = set_priority  # type: ignore[method-assign]
    domain = 100 + os.getpid() % 100  # a domain of its own: another run on the machine must not steer this one
    ours = DdsContext(domain, bridge_config(loopback_config(large_messages=False)))
    user = DdsContext(domain)  # a second participant of the domain ``ours`` configured
    stop = threading.Event()
    thread: threading.Thread | None = None
    try:
        reader = ours.reader(f"{core.namespace}/set_priority", T.KeyValue_, "default")
        writer = user.writer(f"{core.namespace}/set_priority", T.KeyValue_, "default")

        def commands(timeout: float) -> list[tuple[str, str, str]]:
            return [("priority", kv.key, kv.value) for kv in reader.take(16)] if reader.wait(timeout) else []

        loop = ControlLoop(core, lambda d: None, commands, period_s=1.0)
        thread = threading.Thread(target=loop.run, args=(stop,), name="ros2-control", daemon=True)
        thread.start()
        deadline = time.monotonic() + 10
        while writer.matched() < 1 and time.monotonic() < deadline:  # discovery before the first command
            time.sleep(0.05)
        if writer.matched() < 1:
            raise RuntimeError("the ROS 2 door's DDS writer found no reader in 10 s (discovery on loopback)")

        def publish(head: str, cam: str, p: int) -> None:
            log(f"ros2: {head}@{cam} = {p} written at {time.monotonic():.3f}")
            writer.write(T.KeyValue_(f"{head}@{cam}", str(p)))

        yield publish
    finally:
        stop.set()
        if thread is not None:
            thread.join(timeout=5)  # before its reader goes
        user.close()
        ours.close()


def _change(
    eng: Any, stream: _Stream, door: str, head: str, cam: str, top: int, changes: int, settle: float
) -> list[dict[str, Any]]:
    """Per call raising (head, cam) to ``top``: the milliseconds until its first run under the new order (None: none
    within 10 s), and the throttle cap the lane had before (None: it was not throttled, so the call changed nothing
    it could show)."""
    from vpengine.bench.paper.harness import log

    out = []
    with _door(door, eng) as set_priority:
        for _ in range(changes):
            eng.set_priority(head, 0, camera=cam)  # back among the others: throttled again
            time.sleep(settle)
            cap = eng.stats()["cameras"][cam][head]["cap_hz"]
            t0 = time.monotonic()
            arrived = stream.watch(head, cam, t0)
            set_priority(head, cam, top)
            at = arrived(10.0)
            if at is None:  # kept as a result, with what shows where it stuck: did the priority arrive? did it run?
                lane = eng.stats()["cameras"][cam][head]
                out.append({"ms": None, "cap_hz_before": cap} | {k: lane[k] for k in ("priority", "runs", "cap_hz")})
                log(f"{door}: {head}@{cam} gave no output of a later frame within 10 s: {out[-1]}")
                continue
            out.append({"ms": (at - t0) * 1e3, "cap_hz_before": cap})
        eng.set_priority(head, 0, camera=cam)
    log(f"change through {door}: " + ", ".join(f"{c['ms'] or float('nan'):.0f} ms" for c in out))
    log(f"  {head}@{cam}'s caps before each change: " + ", ".join(str(c["cap_hz_before"]) for c in out))
    return out


def _config(base: Any, cameras: int) -> Any:
    from vpengine.config import load_config

    return load_config(base.model_dump() | {"cameras": [{"name": f"cam{i}"} for i in range(cameras)]})


def main(args: argparse.Namespace) -> int:
    from vpengine.bench.common import write_results
    from vpengine.bench.paper.harness import Bench, log
    from vpengine.config import load_config
    from vpengine.engine import Engine

    if args.cameras < 1:
        raise ValueError(f"--cameras {args.cameras}: at least 1")
    doors = [d.strip() for d in args.doors.split(",") if d.strip()]
    unknown = [d for d in doors if d not in DOORS]
    if unknown:
        raise ValueError(f"--doors: {', '.join(unknown)} not known; accepted: {', '.join(DOORS)}")
    cfg = _config(load_config(args.config, list(args.overrides)), args.cameras)
    names = [h.name for h in cfg.heads]
    head = args.head or names[0]
    if head not in names or len(names) < 2:
        raise ValueError(f"--head {head!r}: one of the config's heads {names}, with another to give way")
    raised = names[-1] if names[-1] != head else names[0]
    res: dict[str, Any] = {"config": args.config, "overrides": list(args.overrides), "mode": cfg.mode}
    res |= {"cameras": args.cameras, "fps_per_camera": args.fps, "head": head, "priority": args.priority}
    out_name = args.name or f"steer_{str(cfg.device).split(':')[0]}"
    with Engine(cfg) as eng:
        first, last = eng.cameras[0], eng.cameras[-1]
        stream = _Stream(eng, Bench(cfg).images(), args.fps)
        try:
            time.sleep(args.settle)
            res["equal"], equal = _phase(eng, args.seconds)
            log("equal priorities: " + _summary(res["equal"], head, first))
            write_results(args.out, out_name, res)  # a run cut short keeps what it measured
            eng.set_priority(head, args.priority, camera=first)
            time.sleep(args.settle)
            res["priority"], raised_span = _phase(eng, args.seconds)
            log(f"{head}@{first} at priority {args.priority}: " + _summary(res["priority"], head, first))
            write_results(args.out, out_name, res)
            res["change"] = {"lane": f"{raised}@{last}", "priority": args.priority + 1, "doors": {}}
            for door in doors:
                res["change"]["doors"][door] = _change(
                    eng, stream, door, raised, last, args.priority + 1, args.changes, args.settle
                )
                write_results(args.out, out_name, res)
            _seen(res["equal"], stream, equal)  # by now the stream has taken what those phases published
            _seen(res["priority"], stream, raised_span)
        finally:
            stream.close()
    print(write_results(args.out, out_name, res))
    return 0
