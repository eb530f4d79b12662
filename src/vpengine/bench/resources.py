"""Resources on a GPU: start time, device memory per extra head (process and thread mode) and CPU use, idle and at
30 Hz.

Device memory is what the driver reports (NVML: every process of the engine, CUDA contexts and our VMM mailboxes
included), measured as the increase over the GPU's usage before the engine started. CPU is the sum over the engine's
processes (psutil), in percent of one core.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from vpengine.arguments import add_overrides_argument


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default="bench", help="engine config; its first head is the template (default: bench)")
    p.add_argument("--heads", default="1,2,3,4", help="head counts to measure (comma separated)")
    p.add_argument("--modes", default="process,thread")
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--seconds", type=float, default=10.0, help="duration of each CPU measurement")
    p.add_argument("--device", default="cuda", help="cuda (default) or cpu (only to try the harness)")
    add_overrides_argument(p, "mps=required", "a field of the engine config")
    p.add_argument("--single", metavar="MODE:N", help=argparse.SUPPRESS)  # one measurement, JSON on stdout


def _config(base: str, n_heads: int, mode: str, h: int, w: int, overrides: list[str]) -> Any:
    from vpengine.config import load_config

    cfg = load_config(base, [f"mode={mode}", "device=cuda", f"input.height={h}", f"input.width={w}", *overrides])
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


def measure(
    config: str, n_heads: int, mode: str, h: int, w: int, seconds: float, overrides: list[str], cpu: bool
) -> dict[str, Any]:
    import psutil
    import torch

    from vpengine.engine import Engine
    from vpengine.engine.stats import processes
    from vpengine.runtime.gpu import device_memory_used, process_memory

    if torch.cuda.is_available():
        torch.cuda.synchronize()
    before = device_memory_used(0)
    frames = [np.random.default_rng(i).integers(0, 255, (h, w, 3), dtype=np.uint8) for i in range(4)]
    out: dict[str, Any] = {"mode": mode, "heads": n_heads}
    engine = Engine(_config(config, n_heads, mode, h, w, overrides))
    t0 = time.monotonic()
    engine.start()  # every worker built, warmed up and serving: what a user waits for
    out["start_s"] = time.monotonic() - t0
    with engine as e:
        for i in range(30):
            e.wait(e.submit(frames[i % 4]), timeout=30)
        time.sleep(0.5)
        used = device_memory_used(0)
        out["device_mem_mb"] = (used - before) / 2**20 if used is not None and before is not None else None
        models = e.stats()["models"]
        names = processes({n: m["pid"] for n, m in models.items()})  # a shared process once (Note [Process groups])
        per = process_memory(0)
        out["per_process_mb"] = {name: per[p] / 2**20 for p, name in names.items() if p in per}
        out["per_model_device_mb"] = {n: m["device_mem_bytes"] / 2**20 for n, m in models.items()}
        if cpu:
            procs = [psutil.Process(p) for p in names]
            time.sleep(1.0)
            c0, t0 = _cpu(procs), time.monotonic()
            time.sleep(seconds)
            out["cpu_idle_pct"] = 100 * (_cpu(procs) - c0) / (time.monotonic() - t0)
            e.results()
            each0 = {p.pid: _cpu([p]) for p in procs}
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
            dt = time.monotonic() - t0
            out["cpu_30hz_pct"] = 100 * (_cpu(procs) - c0) / dt
            out["cpu_30hz_pct_by_process"] = {
                names.get(p.pid, str(p.pid)): 100 * (_cpu([p]) - each0[p.pid]) / dt for p in procs
            }
            st = e.stats()["models"]
            out["runs_30hz"] = {k: v["runs"] for k, v in st.items()}
            out["frames_30hz"] = n
    return out


def isolated(
    config: str, n_heads: int, mode: str, h: int, w: int, seconds: float, overrides: list[str], cpu: bool
) -> dict[str, Any]:
    """``measure`` in a fresh process, so no allocator cache or CUDA context of an earlier run is counted."""
    import json
    import subprocess
    import sys

    cmd = [
        sys.executable,
        "-m",
        "vpengine",  # the console script in a child process, not an import of cli/
        "bench",
        "resources",
        "--config",
        config,
        "--single",
        f"{mode}:{n_heads}:{int(cpu)}",
        "--height",
        str(h),
        "--width",
        str(w),
        "--seconds",
        str(seconds),
    ]
    for o in overrides:
        cmd += ["--set", o]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    if p.returncode != 0 or not lines:
        raise RuntimeError(f"resources measurement {mode} x{n_heads} failed:\n{p.stderr[-3000:]}")
    return dict(json.loads(lines[-1]))


def main(args: argparse.Namespace) -> int:
    import json

    from vpengine.bench.common import write_results

    if args.single:
        mode, n, cpu = args.single.split(":")
        r = measure(
            args.config,
            int(n),
            mode,
            args.height,
            args.width,
            args.seconds,
            args.overrides,
            cpu=bool(int(cpu)),
        )
        print(json.dumps(r), flush=True)
        return 0
    counts = [int(x) for x in args.heads.split(",")]
    rows = []
    for mode in args.modes.split(","):
        for n in counts:
            overrides = [*args.overrides, *([f"device={args.device}"] if args.device != "cuda" else [])]
            r = isolated(args.config, n, mode, args.height, args.width, args.seconds, overrides, cpu=(n == max(counts)))
            rows.append(r)
            extra = (
                ""
                if "cpu_idle_pct" not in r
                else (
                    f", CPU idle {r['cpu_idle_pct']:.1f}% / at 30 Hz {r['cpu_30hz_pct']:.0f}% of one core "
                    f"({', '.join(f'{k} {v:.0f}%' for k, v in r['cpu_30hz_pct_by_process'].items())})"
                )
            )
            mem = "n/a" if r["device_mem_mb"] is None else f"+{r['device_mem_mb']:.0f} MB"
            print(f"{mode:8s} heads={n}: started in {r['start_s']:.1f} s, device memory {mem}{extra}", flush=True)
    summary = {}
    for mode in args.modes.split(","):
        pts = [(r["heads"], r["device_mem_mb"]) for r in rows if r["mode"] == mode and r["device_mem_mb"] is not None]
        if len(pts) >= 2:
            xs, ys = zip(*pts)
            summary[mode] = {"mb_per_extra_head": float(np.polyfit(xs, ys, 1)[0])}
    tag = "_".join(o.replace("=", "-") for o in args.overrides if o.startswith("mps="))
    path = write_results(
        args.out,
        "resources_gpu" + (f"_{tag}" if tag else ""),
        {
            "config": args.config,
            "input": [args.height, args.width],
            "overrides": args.overrides,
            "rows": rows,
            "summary": summary,
        },
    )
    for mode, s in summary.items():
        print(f"{mode}: +{s['mb_per_extra_head']:.0f} MB device memory per extra head")
    print(f"-> {path}")
    return 0
