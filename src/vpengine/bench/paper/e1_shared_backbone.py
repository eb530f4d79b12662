"""E1: one backbone shared by N depth heads (the engine) against N independent full models and against the same
models run one after another in one process (paper: 2.3x over independent models at 8 heads).

The independent models are N engines of one depth head each, always in process mode, fed the same frame; a frame's
latency is the slowest of them. With device times (CUDA), each row also gives the ideal ratio N(b+h)/(b+Nh) from the
backbone's time b and a head's time h: what sharing the backbone saves if nothing else costs anything.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from vpengine.bench.paper.harness import Bench, engine_and_sequential, engines, log, timed


def independent_latency(es: list[Any], imgs: list[np.ndarray], b: Bench) -> dict[str, float]:
    """N independent full pipelines (each its own backbone): a frame goes to all, latency = the slowest."""

    def one(i: int) -> None:
        fids = [e.submit(imgs[i % len(imgs)]) for e in es]
        for e, fid in zip(es, fids):
            e.wait(fid, timeout=120, copy=b.copy)

    return timed(one, b.frames)


def run(b: Bench, imgs: list[np.ndarray], ns: list[int]) -> dict[str, Any]:
    rows = []
    for n in ns:
        shared, sequential, dt = engine_and_sequential(b, [b.head("depth", f"depth{i}") for i in range(n)], imgs)
        singles = [b.config([b.head("depth", "depth")], mode="process") for _ in range(n)]
        with engines(singles) as es:
            indep = independent_latency(es, imgs, b)
        row = {
            "heads": n,
            "engine": shared,
            "independent": indep,
            "sequential": sequential,
            "device_ms": dt,
            "speedup_vs_independent": indep["mean"] / shared["mean"],
            "speedup_vs_sequential": sequential["mean"] / shared["mean"],
        }
        if dt:
            bb, h = dt["foundation"], dt["depth0"]
            row["ideal_vs_independent"] = n * (bb + h) / (bb + n * h)
        rows.append(row)
        log(
            f"E1 N={n}: engine ({b.label}) {shared['mean']:.1f} ms on {shared['cpu_cores']:.2f} cores, independent {indep['mean']:.1f} ms "
            f"({row['speedup_vs_independent']:.2f}x), sequential {sequential['mean']:.1f} ms "
            f"({row['speedup_vs_sequential']:.2f}x)" + (f", ideal {row['ideal_vs_independent']:.2f}x" if dt else "")
        )
    return {"rows": rows}
