"""Tiny pipeline throughput in process and thread mode.

Two numbers per mode: lockstep frames per second (submit, wait for every head, repeat: the end-to-end rate with one
frame in flight) and streaming rates (submit as fast as possible for a while: how often each model runs).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default="tiny", help="engine config (default: the shipped tiny config)")
    p.add_argument("--frames", type=int, default=300, help="lockstep frames per mode")
    p.add_argument("--seconds", type=float, default=5.0, help="streaming duration per mode")


def measure(config: str, mode: str, frames: int, seconds: float) -> dict[str, Any]:
    from vpengine.engine import Engine

    with Engine(config, [f"mode={mode}"]) as eng:
        h, w = eng.config.input.height, eng.config.input.width
        rng = np.random.default_rng(0)
        imgs = [rng.integers(0, 255, (h, w, 3), dtype=np.uint8) for _ in range(8)]
        for i in range(10):  # warm-up
            eng.wait(eng.submit(imgs[i % 8]), timeout=10)
        lat = []
        t0 = time.monotonic()
        for i in range(frames):
            t = time.monotonic()
            eng.wait(eng.submit(imgs[i % 8]), timeout=10)
            lat.append(time.monotonic() - t)
        lockstep_fps = frames / (time.monotonic() - t0)
        before = {n: m["runs"] for n, m in eng.stats()["models"].items()}
        t0 = time.monotonic()
        n_sub = 0
        while time.monotonic() - t0 < seconds:
            eng.submit(imgs[n_sub % 8])
            n_sub += 1
            time.sleep(0.0005)
        dur = time.monotonic() - t0
        time.sleep(0.3)
        after = eng.stats()["models"]
        return {
            "mode": mode,
            "lockstep_fps": lockstep_fps,
            "lockstep_latency_ms": {
                "p50": float(np.median(lat) * 1e3),
                "p99": float(np.percentile(lat, 99) * 1e3),
            },
            "stream_submit_hz": n_sub / dur,
            "stream_model_hz": {n: (after[n]["runs"] - before[n]) / dur for n in after},
        }


def main(args: argparse.Namespace) -> int:
    from vpengine.bench.common import write_results

    results = [measure(args.config, mode, args.frames, args.seconds) for mode in ("process", "thread")]
    path = write_results(args.out, "pipeline_tiny", {"config": args.config, "results": results})
    for r in results:
        rates = ", ".join(f"{k} {v:.0f} Hz" for k, v in r["stream_model_hz"].items())
        print(
            f"{r['mode']:8s} lockstep {r['lockstep_fps']:.0f} frames/s (p50 {r['lockstep_latency_ms']['p50']:.1f} ms,"
            f" p99 {r['lockstep_latency_ms']['p99']:.1f} ms); streaming: {rates}"
        )
    print(f"-> {path}")
    return 0
