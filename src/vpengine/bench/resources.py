"""Resources on a GPU: device memory per extra head (process and thread mode) and CPU use, idle and at 30 Hz.

Device memory is what the driver reports (NVML: every process of the engine, CUDA contexts and our VMM mailboxes
included), measured as the increase over the GPU's usage before the engine started. CPU is the sum over the engine's
processes (psutil), in percent of one core.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default="configs/tiny.yaml", help="engine config; its first head is the template")
    p.add_argument("--heads", default="1,2,3,4", help="head counts to measure (comma separated)")
    p.add_argument("--modes", default="process,thread")
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--seconds", type=float, default=10.0, help="duration of each CPU measurement")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")


def _config(base: str, n_heads: int, mode: str, h: int, w: int, overrides: list[str]) -> Any:
    from vpengine.config import load_config

    cfg = load_config(base, [*overrides, f"mode={mode}", "device=cuda", f"input.height={h}", f"input.width={w}"])
    template = cfg.heads[0].model_dump()
    heads = [{**template, "name": f"head{i}"} for i in range(n_heads)]
    return load_config(cfg.model_dump() | {"heads": heads})


def _cpu(procs: list[Any]) -> float:
    total = 0.0
    for p in procs:
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except Exception:
            pass
    return total


def measure(config: str, n_heads: int, mode: str, h: int, w: int, seconds: float, overrides: list[str],
            cpu: bool) -> dict[str, Any]:
    import psutil
    import torch

    from vpengine.engine import Engine
    from vpengine.runtime.gpu import device_memory_used, process_memory

    torch.cuda.synchronize()
    before = device_memory_used(0)
    frames = [np.random.default_rng(i).integers(0, 255, (h, w, 3), dtype=np.uint8) for i in range(4)]
    out: dict[str, Any] = {"mode": mode, "heads": n_heads}
    with Engine(_config(config, n_heads, mode, h, w, overrides)) as e:
        for i in range(30):
            e.wait(e.submit(frames[i % 4]), timeout=30)
        time.sleep(0.5)
        used = device_memory_used(0)
        out["device_mem_mb"] = (used - before) / 2**20 if used is not None and before is not None else None
        pids = {m["pid"] for m in e.stats()["models"].values()}
        per = process_memory(0)
        out["per_process_mb"] = {str(p): per[p] / 2**20 for p in pids | {psutil.Process().pid} if p in per}
        if cpu:
            procs = [psutil.Process(p) for p in pids | {psutil.Process().pid}]
            time.sleep(1.0)
            c0, t0 = _cpu(procs), time.monotonic()
            time.sleep(seconds)
            out["cpu_idle_pct"] = 100 * (_cpu(procs) - c0) / (time.monotonic() - t0)
            e.results()
            c0, t0 = _cpu(procs), time.monotonic()
            n = 0
            while time.monotonic() - t0 < seconds:
                target = t0 + n / 30.0
                delay = target - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                e.submit(frames[n % 4])
                n += 1
                e.results()
            out["cpu_30hz_pct"] = 100 * (_cpu(procs) - c0) / (time.monotonic() - t0)
            st = e.stats()["models"]
            out["runs_30hz"] = {k: v["runs"] for k, v in st.items()}
            out["frames_30hz"] = n
    return out


def main(args: argparse.Namespace) -> int:
    from vpengine.bench.common import write_results

    counts = [int(x) for x in args.heads.split(",")]
    rows = []
    for mode in args.modes.split(","):
        for n in counts:
            r = measure(args.config, n, mode, args.height, args.width, args.seconds, args.overrides,
                        cpu=(n == max(counts)))
            rows.append(r)
            extra = "" if "cpu_idle_pct" not in r else (
                f", CPU idle {r['cpu_idle_pct']:.1f}% / at 30 Hz {r['cpu_30hz_pct']:.0f}% of one core")
            print(f"{mode:8s} heads={n}: device memory +{r['device_mem_mb']:.0f} MB{extra}", flush=True)
    summary = {}
    for mode in args.modes.split(","):
        pts = [(r["heads"], r["device_mem_mb"]) for r in rows if r["mode"] == mode and r["device_mem_mb"] is not None]
        if len(pts) >= 2:
            xs, ys = zip(*pts)
            summary[mode] = {"mb_per_extra_head": float(np.polyfit(xs, ys, 1)[0])}
    path = write_results(args.out, "resources_gpu", {"config": args.config, "input": [args.height, args.width],
                                                     "rows": rows, "summary": summary})
    for mode, s in summary.items():
        print(f"{mode}: +{s['mb_per_extra_head']:.0f} MB device memory per extra head")
    print(f"-> {path}")
    return 0
