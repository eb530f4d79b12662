"""E4: rate limits. Six depth heads limited to 5, 10, 15, 20, 25 and 30 Hz take 10 s of 30 Hz input: each must run
R x 10 times, +-1 (paper: +-1), after an idle second that its schedule must restart from cleanly. A head cannot run
on a frame the backbone skipped, so the ideal is at most the backbone's runs."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from vpengine.bench.paper.harness import Bench, engines, log

RATES = (5, 10, 15, 20, 25, 30)


def run(b: Bench, imgs: list[np.ndarray], seconds: float = 10.0) -> dict[str, Any]:
    heads = [b.head("depth", f"r{r}", rate_hz=r) for r in RATES]
    with engines([b.config(heads)]) as (eng,):
        for i in range(5):
            eng.wait(eng.submit(imgs[i % len(imgs)]), timeout=120)
        before = {k: v["runs"] for k, v in eng.stats()["models"].items()}
        time.sleep(1.0)  # idle gap: the schedule must restart cleanly
        t0 = time.monotonic()
        n = 0
        while n / 30.0 < seconds:
            d = t0 + n / 30.0 - time.monotonic()
            if d > 0:
                time.sleep(d)
            eng.submit(imgs[n % len(imgs)])
            n += 1
        time.sleep(0.5)
        st = eng.stats()["models"]
    fm_runs = st["foundation"]["runs"] - before["foundation"]
    rows = []
    for r in RATES:
        runs = st[f"r{r}"]["runs"] - before[f"r{r}"]
        ideal = min(r * seconds, fm_runs)
        rows.append(
            {
                "rate_hz": r,
                "runs": runs,
                "ideal": ideal,
                "error": runs - ideal,
                "skipped": st[f"r{r}"]["skipped"],
            }
        )
    log(
        f"E4 (backbone ran {fm_runs} of {n} frames) "
        + ", ".join(f"{x['rate_hz']} Hz: {x['runs']} ({x['error']:+.0f})" for x in rows)
    )
    return {"rows": rows, "input_frames": n, "foundation_runs": fm_runs, "input_seconds": seconds}
