"""E2: N detection heads on one backbone, run in parallel by the engine against one after another in one process
(paper: 3.3x at 8 heads). Each row also holds each model's device time alone (CUDA events; empty off CUDA)."""

from __future__ import annotations

from typing import Any

import numpy as np

from vpengine.bench.paper.harness import Bench, engine_and_sequential, log


def run(b: Bench, imgs: list[np.ndarray], ns: list[int]) -> dict[str, Any]:
    rows = []
    for n in ns:
        parallel, sequential, dt = engine_and_sequential(b, [b.head("det", f"det{i}") for i in range(n)], imgs)
        rows.append(
            {
                "heads": n,
                "engine": parallel,
                "sequential": sequential,
                "device_ms": dt,
                "speedup_vs_sequential": sequential["mean"] / parallel["mean"],
            }
        )
        log(
            f"E2 N={n}: engine ({b.label}) {parallel['mean']:.1f} ms, sequential {sequential['mean']:.1f} ms "
            f"({rows[-1]['speedup_vs_sequential']:.2f}x)"
        )
    return {"rows": rows}
