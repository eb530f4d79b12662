"""What the live view (:mod:`vpengine.web`) costs the engine: E5's stream with and without a viewer.

The E5 protocol (a stream of frames at 30 Hz into a depth + segmentation + detection pipeline, every result taken
from ``Engine.results``; latency is submit -> result on the host) runs in alternating phases with the view served
throughout: ``off``, nobody looks (the server only listens), and ``on``, a viewer in its own process asks what the
open page asks (the stats every ``STATS_PERIOD_S``, each head's picture ``PICTURE_PERIOD_S`` after the previous one
arrived, 320 pixels wide, over kept-alive connections). Phases alternate ``rounds`` times, so drift on the machine
shows as spread, not as overhead. Per condition: latency percentiles of the frame (every head answered) and of
each head, frames some head never answered, the engine's CPU (this process, where the server runs, and its workers), and
the viewer's request times and CPU (on a small machine the viewer's own CPU competes with the engine; a browser on
another computer would not).

::

    vpengine bench web                                                  # tiny models on the CPU
    vpengine bench web -c configs/dinov2s_depth_seg_det.yaml --random-weights --device cuda \\
        --set heads.seg.rate_hz=null --set heads.det.rate_hz=null --name web_overhead_h100
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time
from typing import Any

import numpy as np

from vpengine.arguments import add_overrides_argument


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", "-c", default="tiny", help="engine config (default: the shipped tiny config)")
    add_overrides_argument(p, "heads.seg.rate_hz=null")
    p.add_argument("--device", help="override the config's device (cpu, cuda, cuda:N)")
    p.add_argument("--mode", choices=["process", "thread"], help="override the config's mode")
    p.add_argument("--random-weights", action="store_true", help="use random weights instead of checkpoints")
    p.add_argument("--fps", type=float, default=30.0, help="input rate (default 30 Hz, as E5)")
    p.add_argument("--seconds", type=float, default=20.0, help="length of each phase (default 20 s)")
    p.add_argument("--rounds", type=int, default=3, help="off/on phase pairs (default 3)")
    p.add_argument("--name", default="web_overhead_cpu", help="results file name (default: web_overhead_cpu)")


# ------------------------------------------------------------------------------------------------ viewer
def _viewer(url: str, heads: list[str], periods: tuple[float, float], stop: Any, report: Any) -> None:
    """The open page's requests, from a process of its own (a browser is one), until ``stop`` is set; ``periods``:
    the page's (stats, picture) refresh periods."""
    import http.client
    import threading
    from urllib.parse import urlsplit

    stats_period, picture_period = periods
    u = urlsplit(url)
    times: dict[str, list[float]] = {"stats": [], "picture": []}
    errors: list[str] = []

    def loop(path: str, kind: str, period: float, after_answer: bool) -> None:
        conn = http.client.HTTPConnection(u.hostname or "127.0.0.1", u.port, timeout=30)
        next_t = time.monotonic()
        while not stop.is_set():
            t0 = time.monotonic()
            try:
                conn.request("GET", path)
                r = conn.getresponse()
                r.read()
                if r.status not in (200, 204):
                    errors.append(f"{path}: {r.status}")
            except OSError as e:
                errors.append(f"{path}: {e}")
                conn.close()
            times[kind].append(time.monotonic() - t0)
            next_t = (time.monotonic() if after_answer else next_t) + period  # the page: setTimeout after load
            stop.wait(max(0.0, next_t - time.monotonic()))
        conn.close()

    threads = [threading.Thread(target=loop, args=("/api/stats", "stats", stats_period, False))]
    threads += [
        threading.Thread(target=loop, args=(f"/api/latest/{h}.jpg?width=320", "picture", picture_period, True))
        for h in heads
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    report.put({"times": times, "errors": errors[:20], "n_errors": len(errors)})


# ------------------------------------------------------------------------------------------------- phases
def _pct(values: list[float]) -> dict[str, float | int | None]:
    a = np.asarray(values, dtype=float) * 1e3
    if not len(a):
        return {"p50": None, "p90": None, "p99": None, "mean": None, "n": 0}
    p = np.percentile(a, [50, 90, 99])
    return {"p50": float(p[0]), "p90": float(p[1]), "p99": float(p[2]), "mean": float(a.mean()), "n": len(a)}


def _cpu_s(exclude: set[int]) -> float:
    """CPU seconds of this process and its worker processes so far (not the viewer)."""
    import psutil

    me = psutil.Process()
    total = sum(me.cpu_times()[:2])
    for child in me.children(recursive=True):
        if child.pid in exclude:
            continue
        try:
            total += sum(child.cpu_times()[:2])
        except psutil.Error:
            pass
    return total


def _phase(
    engine: Any,
    view: Any,
    imgs: list[np.ndarray],
    recent: dict[int, np.ndarray],
    viewer: bool,
    seconds: float,
    fps: float,
) -> dict[str, Any]:
    heads = list(engine.plan.heads)
    per_frame: dict[int, dict[str, float]] = {}
    lat: dict[str, list[float]] = {h: [] for h in heads}

    def take(timeout: float) -> int:
        rs = engine.results(timeout=timeout)
        for r in rs:
            if r.frame_id in per_frame:
                per_frame[r.frame_id][r.head] = r.latency
                lat[r.head].append(r.latency)
        return len(rs)

    import psutil

    from vpengine.web import PICTURE_PERIOD_S, STATS_PERIOD_S

    ctx = mp.get_context("spawn")
    proc: Any = None
    stop: Any = None
    report: Any = None
    if viewer:
        stop, report = ctx.Event(), ctx.Queue()
        periods = (STATS_PERIOD_S, PICTURE_PERIOD_S)
        proc = ctx.Process(target=_viewer, args=(view.url, heads, periods, stop, report), daemon=True)
        proc.start()
        time.sleep(1.0)  # the viewer's interpreter is up and polling before the phase counts
    take(0)
    made0 = view.pictures.made
    viewer_cpu0 = sum(psutil.Process(proc.pid).cpu_times()[:2]) if proc else 0.0
    cpu0, t0 = _cpu_s({proc.pid} if proc else set()), time.monotonic()
    n = round(seconds * fps)
    for k in range(n):
        t = t0 + k / fps
        while (now := time.monotonic()) < t:
            take(t - now)
        img = imgs[k % len(imgs)]
        fid = engine.submit(img)
        per_frame[fid] = {}
        recent[fid] = img
        if len(recent) > 64:
            recent.pop(next(iter(recent)))
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and take(0.5):
        pass
    wall = time.monotonic() - t0
    cpu = _cpu_s({proc.pid} if proc else set()) - cpu0
    viewer_cpu = sum(psutil.Process(proc.pid).cpu_times()[:2]) - viewer_cpu0 if proc else 0.0
    out: dict[str, Any] = {
        "viewer": viewer,
        "frames": n,
        "frame_latency_ms": _pct([max(v.values()) for v in per_frame.values() if len(v) == len(heads)]),
        "head_latency_ms": {h: _pct(v) for h, v in lat.items()},
        "frames_incomplete": sum(len(v) < len(heads) for v in per_frame.values()),
        "engine_cpu_pct_of_one_core": 100.0 * cpu / wall,
        "pictures_made": view.pictures.made - made0,
    }
    if proc is not None:
        stop.set()
        got = report.get(timeout=60)
        proc.join(30)
        out["viewer_requests"] = {
            "stats": _pct(got["times"]["stats"]),
            "picture": _pct(got["times"]["picture"]),
            "errors": got["n_errors"],
            "first_errors": got["errors"],
            "viewer_cpu_pct_of_one_core": 100.0 * viewer_cpu / wall,
        }
    return out


def _per_phase(phases: list[dict[str, Any]], key: str) -> dict[str, list[float | None]]:
    return {f"{s}_per_phase": [p[key][s] for p in phases] for s in ("p50", "p99", "mean")}


def measure(config: str, overrides: list[str], seconds: float, rounds: int, fps: float) -> dict[str, Any]:
    from vpengine.engine import Engine
    from vpengine.io.sources import SyntheticSource
    from vpengine.web import serve

    engine = Engine(config, overrides)
    cfg = engine.config
    src = SyntheticSource(cfg.input.width, cfg.input.height, fps, 8)
    imgs = [src.render(i * 3) for i in range(8)]
    if cfg.input.color == "rgb":
        imgs = [np.ascontiguousarray(i[..., ::-1]) for i in imgs]
    recent: dict[int, np.ndarray] = {}
    phases: list[dict[str, Any]] = []
    with engine, serve(engine, port=0, frames=recent.get, frame_color=cfg.input.color) as view:
        for i in range(30):
            engine.wait(engine.submit(imgs[i % 8]), timeout=120)
        for r in range(rounds):
            for viewer in (False, True):
                phases.append(_phase(engine, view, imgs, recent, viewer, seconds, fps))
                p = phases[-1]["frame_latency_ms"]
                print(
                    f"round {r + 1}/{rounds} viewer {'on ' if viewer else 'off'}: frame p50 {p['p50']:.2f} ms, "
                    f"p99 {p['p99']:.2f} ms, engine CPU {phases[-1]['engine_cpu_pct_of_one_core']:.0f}%",
                    flush=True,
                )
        stats = engine.stats()
    summary: dict[str, Any] = {}
    for viewer, label in ((False, "off"), (True, "on")):
        ps = [p for p in phases if p["viewer"] is viewer]
        summary[label] = {
            "frame_latency_ms": _per_phase(ps, "frame_latency_ms"),
            "frames_incomplete": sum(p["frames_incomplete"] for p in ps),
            "engine_cpu_pct_of_one_core": [p["engine_cpu_pct_of_one_core"] for p in ps],
        }
    off, on = (np.median(summary[k]["frame_latency_ms"]["p50_per_phase"]) for k in ("off", "on"))
    off99, on99 = (np.median(summary[k]["frame_latency_ms"]["p99_per_phase"]) for k in ("off", "on"))
    cpu_off, cpu_on = (np.median(summary[k]["engine_cpu_pct_of_one_core"]) for k in ("off", "on"))
    summary["overhead"] = {
        "frame_p50_ms": float(on - off),
        "frame_p50_pct": float(100 * (on - off) / off),
        "frame_p99_ms": float(on99 - off99),
        "engine_cpu_pct_of_one_core": float(cpu_on - cpu_off),
        "note": "medians over the phases of each condition; 'on' minus 'off'",
    }
    return {
        "config": cfg.name,
        "mode": cfg.mode,
        "device": cfg.device,
        "input": [cfg.input.width, cfg.input.height],
        "heads": list(engine.plan.heads),
        "fps": fps,
        "seconds_per_phase": seconds,
        "rounds": rounds,
        "summary": summary,
        "phases": phases,
        "skipped": {n: m["skipped"] for n, m in stats["models"].items()},
    }


def main(args: argparse.Namespace) -> int:
    from vpengine.bench.common import write_results

    if args.rounds < 1 or args.seconds <= 0 or args.fps <= 0:
        raise ValueError(
            f"--rounds must be >= 1 and --seconds, --fps > 0; got {args.rounds}, {args.seconds}, {args.fps}"
        )
    overrides = list(args.overrides)
    overrides += [f"device={args.device}"] if args.device else []
    overrides += [f"mode={args.mode}"] if args.mode else []
    overrides += ["weights.random_weights=true"] if args.random_weights else []
    res = measure(args.config, overrides, args.seconds, args.rounds, args.fps)
    path = write_results(args.out, args.name, {"config_file": args.config, "overrides": overrides, **res})
    o = res["summary"]["overhead"]
    print(
        f"viewer on vs off: frame p50 {o['frame_p50_ms']:+.2f} ms ({o['frame_p50_pct']:+.1f}%), p99 "
        f"{o['frame_p99_ms']:+.2f} ms, engine CPU {o['engine_cpu_pct_of_one_core']:+.1f}% of a core -> {path}"
    )
    return 0
