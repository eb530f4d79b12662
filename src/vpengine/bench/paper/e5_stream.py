"""E5: a long 30 Hz stream through depth, segmentation and detection heads: each head's latency (submit -> result
on the host), the latency of a frame's three results, frames lost, and device memory once a second, which must stay
flat (Note: the engine allocates nothing after start, so any growth is a leak)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from vpengine.bench.paper.harness import Bench, EngineCpu, engines, log, pct

HEADS = ("depth", "seg", "det")


def run(b: Bench, imgs: list[np.ndarray], n_frames: int) -> dict[str, Any]:
    import torch

    from vpengine.runtime.gpu import device_memory_used, process_memory

    lat: dict[str, list[float]] = {h: [] for h in HEADS}
    per_frame: dict[int, dict[str, float]] = {}
    memory: list[dict[str, Any]] = []
    device = torch.device(b.device)
    index = (device.index or 0) if device.type == "cuda" else None

    def take(results: list[Any]) -> None:
        for r in results:
            lat[r.head].append(r.latency)
            per_frame.setdefault(r.frame_id, {})[r.head] = r.latency

    with engines([b.config([b.head(h, h) for h in HEADS])]) as (eng,):
        for i in range(30):
            eng.wait(eng.submit(imgs[i % len(imgs)]), timeout=120)
        eng.results()
        pids = [m["pid"] for m in eng.stats()["models"].values()]
        cpu = EngineCpu(eng)
        t0 = time.monotonic()
        next_mem = t0
        for k in range(n_frames):
            t = t0 + k / 30.0
            while (now := time.monotonic()) < t:
                take(eng.results(timeout=t - now, copy=b.copy))
            eng.submit(imgs[k % len(imgs)])
            if index is not None and time.monotonic() >= next_mem:
                per = process_memory(index)
                memory.append(
                    {
                        "t": time.monotonic() - t0,
                        "frame": k,
                        "device_used": device_memory_used(index),
                        "workers": [per.get(p) for p in pids],
                    }
                )
                next_mem += 1.0
            if k and k % 1000 == 0:
                log(f"E5 {k}/{n_frames} frames")
        cpu_cores = cpu.cores()  # over the stream, before the drain below
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            rs = eng.results(timeout=0.5, copy=b.copy)
            take(rs)
            if not rs:
                break
        st = eng.stats()
    complete = [max(v.values()) for v in per_frame.values() if len(v) == len(HEADS)]
    lost = {h: n_frames - len(v) for h, v in lat.items()}
    used = [m["device_used"] for m in memory if m["device_used"] is not None]
    steady = used[len(used) // 10 :]  # after the first tenth: allocator warm-up is not a leak
    out = {
        "frames": n_frames,
        "per_head_latency_ms": {h: pct(v) for h, v in lat.items()},
        "all_three_latency_ms": pct(complete),
        "cpu_cores": cpu_cores,
        "frames_lost": lost,
        "loss_pct": {h: 100.0 * v / n_frames for h, v in lost.items()},
        "results_missed": {h: st["results"][h]["missed"] for h in HEADS},
        "skipped": {h: st["models"][h]["skipped"] for h in ("foundation", *HEADS)},
        "memory": memory,
        "memory_flat": max(steady) == min(steady) if steady else None,  # None: not measured (no NVML, no CUDA)
    }
    a3 = out["all_three_latency_ms"]
    log(
        f"E5 {n_frames} frames at 30 Hz: all three heads p50 {a3['p50']:.1f} ms p99 {a3['p99']:.1f} ms; "
        f"lost {out['loss_pct']}; memory flat: {out['memory_flat']}; CPU {100 * cpu_cores:.0f}% of a core"
    )
    return out
