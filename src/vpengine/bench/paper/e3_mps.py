"""E3: CUDA MPS off against on, with 4 and 8 detection heads and 4 and 8 depth heads, in process mode (paper: +39%
at 4 heads, +77% at 8). The daemon is the one reachable, or a private one started for the run and stopped after."""

from __future__ import annotations

from typing import Any

import numpy as np

from vpengine.bench.paper.harness import Bench, engines, lockstep, log, mps_daemon


def check(b: Bench) -> None:
    if not b.on_cuda:
        raise ValueError(f"E3 compares CUDA MPS off and on: it needs device cuda, and the config has {b.device!r}")


def run(b: Bench, imgs: list[np.ndarray], ns: tuple[int, ...] = (4, 8)) -> dict[str, Any]:
    check(b)
    rows = []
    with mps_daemon() as daemon:
        for kind in ("det", "depth"):
            for n in ns:
                heads = [b.head(kind, f"{kind}{i}") for i in range(n)]
                res = {}
                for setting in ("off", "required"):
                    cfg = b.config(heads, mode="process", mps=setting)
                    with engines([cfg]) as (eng,):
                        res[setting] = lockstep(eng, imgs, b)
                        res[setting]["workers_on_mps"] = len(eng.stats()["engine"]["mps"]["workers_on_mps"])
                gain = res["off"]["mean"] / res["required"]["mean"] - 1
                rows.append(
                    {
                        "head": kind,
                        "heads": n,
                        "mps_off": res["off"],
                        "mps_on": res["required"],
                        "throughput_gain": gain,
                    }
                )
                log(
                    f"E3 {kind} N={n}: MPS off {res['off']['hz']:.1f} Hz, on {res['required']['hz']:.1f} Hz "
                    f"({gain:+.0%}, {res['required']['workers_on_mps']} workers on MPS)"
                )
    return {"rows": rows, "mps_pipe_directory": daemon}
