"""Heads added and removed while a stream runs (``Engine.add_head``, ``Engine.remove_head``; Note [Heads at run time]
in runtime/lanes.py).

The config's heads but one serve a stream of synthetic frames at ``--fps``; the other (``--head``, by default the
config's last: the detection head of the shipped bench config) is added and removed ``--cycles`` times, ``--hold``
seconds apart. Per cycle: how long ``add_head`` took (build, warm-up, CUDA graphs), the longest gap between two
outputs of each serving head from the start of the add until a second after it (against the frame period: a head
that kept serving shows gaps of about one period), what stopped this whole process's interpreter meanwhile (the
longest gap of a thread that only wakes every 10 ms, and the full garbage collections and the longest one: Note
[Building beside serving threads] in runtime/threads.py), and the device memory in use before the add, with the
head, and after its removal (on CUDA: the whole device's, every worker process included). Over all cycles: the open
file descriptors, threads and child processes of this process before and after.

::

    vpengine bench heads -c configs/tiny.yaml --set device=cpu --cycles 2 --hold 1   # anywhere
    vpengine bench heads --set mode=thread                                              # a GPU machine
"""

from __future__ import annotations

import argparse
import gc
import os
import threading
import time
from typing import Any

import numpy as np

from vpengine.arguments import add_overrides_argument


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", "-c", default="bench", help="engine config (default: the shipped bench config)")
    add_overrides_argument(p, "mode=thread")
    p.add_argument("--head", default=None, help="the config's head to add and remove (default: its last)")
    p.add_argument("--fps", type=float, default=30.0, help="the stream's rate (default 30 Hz)")
    p.add_argument("--cycles", type=int, default=5, help="add/remove cycles (default 5)")
    p.add_argument("--hold", type=float, default=2.0, help="seconds between an add and a remove (default 2)")
    p.add_argument("--name", default=None, help="results file name (default: heads_<device>)")


def _device_used(device: str) -> int | None:
    if not device.startswith("cuda"):
        return None
    import torch

    free, total = torch.cuda.mem_get_info()
    return int(total - free)


def _children() -> int:
    from vpengine.bench.common import proc_stat

    me, n = str(os.getpid()), 0
    for pid in os.listdir("/proc"):
        if pid.isdigit():
            try:
                n += proc_stat(f"/proc/{pid}/stat")[1] == me  # ppid
            except OSError:
                continue
    return n


def _usage() -> dict[str, int]:
    return {"fds": len(os.listdir("/proc/self/fd")), "threads": threading.active_count(), "children": _children()}


class _Pauses:
    """When this process's interpreter stopped: a thread that wakes every 10 ms notes each wake-up, and every full
    garbage collection is noted with its length."""

    def __init__(self) -> None:
        self.wakes: list[float] = []
        self.collections: list[tuple[float, float]] = []  # (start, seconds)
        self._started = 0.0
        self.stop = threading.Event()
        gc.callbacks.append(self._collected)
        self.thread = threading.Thread(target=self._wake, daemon=True)
        self.thread.start()

    def _wake(self) -> None:
        while not self.stop.wait(0.01):
            self.wakes.append(time.monotonic())

    def _collected(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self._started = time.monotonic()
        elif info["generation"] == 2:
            self.collections.append((self._started, time.monotonic() - self._started))

    def between(self, t0: float, t1: float) -> dict[str, Any]:
        t = np.asarray([w for w in self.wakes if t0 <= w <= t1])
        full = [d for start, d in self.collections if t0 <= start <= t1]
        return {
            "longest_stop_ms": float(np.diff(t).max() * 1000) if len(t) > 1 else float("nan"),
            "full_gcs": len(full),
            "longest_full_gc_ms": max(full, default=0.0) * 1000,
        }

    def close(self) -> None:
        self.stop.set()
        gc.callbacks.remove(self._collected)
        self.thread.join(1.0)


class _Stream:
    """Frames at ``fps`` from one thread, every result's publish time per head from another."""

    def __init__(self, engine: Any, imgs: list[np.ndarray], fps: float) -> None:
        self.engine, self.imgs, self.fps = engine, imgs, fps
        self.published: dict[str, list[float]] = {}
        self.stop = threading.Event()
        self.threads = [threading.Thread(target=f, daemon=True) for f in (self._feed, self._collect)]
        for t in self.threads:
            t.start()

    def _feed(self) -> None:
        t0, n = time.monotonic(), 0
        while not self.stop.is_set():
            self.engine.submit(self.imgs[n % len(self.imgs)])
            n += 1
            self.stop.wait(max(0.0, t0 + n / self.fps - time.monotonic()))

    def _collect(self) -> None:
        while not self.stop.is_set():
            for r in self.engine.results(timeout=0.1):
                self.published.setdefault(r.head, []).append(r.t_publish)

    def longest_gap_ms(self, head: str, t0: float, t1: float) -> float:
        t = np.asarray(self.published.get(head, []))
        t = t[(t >= t0) & (t <= t1)]
        return float(np.diff(t).max() * 1000) if len(t) > 1 else float("nan")

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(5.0)


def main(args: argparse.Namespace) -> int:
    from vpengine.bench.common import write_results
    from vpengine.bench.paper.harness import Bench, log
    from vpengine.config import load_config
    from vpengine.engine import Engine

    base = load_config(args.config, list(args.overrides))
    names = [h.name for h in base.heads]
    name = args.head or names[-1]
    if name not in names or len(names) < 2:
        raise ValueError(f"--head {name!r}: one of the config's heads {names}, with another left to serve")
    added = next(h for h in base.heads if h.name == name).model_dump(mode="json", exclude_unset=True)
    serving = [h.model_dump() for h in base.heads if h.name != name]
    cfg = load_config(base.model_dump() | {"heads": serving})
    period_ms = 1000 / args.fps
    res: dict[str, Any] = {"config": args.config, "overrides": list(args.overrides), "mode": cfg.mode}
    res |= {"serving": [h["name"] for h in serving], "added": name, "fps": args.fps, "cycles": []}
    out_name = args.name or f"heads_{str(cfg.device).split(':')[0]}"
    with Engine(cfg) as eng:
        stream = _Stream(eng, Bench(cfg).images(), args.fps)
        pauses = _Pauses()
        try:
            time.sleep(args.hold)
            res["before"] = _usage()
            for k in range(args.cycles):
                before = _device_used(cfg.device)
                t0 = time.monotonic()
                eng.add_head(added)
                t1 = time.monotonic()
                time.sleep(args.hold)
                runs = eng.stats()["models"][name]["runs"]
                with_head = _device_used(cfg.device)
                eng.remove_head(name)
                time.sleep(args.hold)
                gaps = {h: stream.longest_gap_ms(h, t0, t1 + 1.0) for h in res["serving"]}
                cycle = {"add_s": t1 - t0, "runs": runs, "longest_gap_ms": gaps, "period_ms": period_ms}
                cycle |= {"interpreter": pauses.between(t0, t1 + 1.0)}
                cycle |= {"device_bytes": {"before": before, "with_head": with_head, "after": _device_used(cfg.device)}}
                res["cycles"].append(cycle)
                log(
                    f"cycle {k + 1}: add {t1 - t0:.1f} s, {runs} runs, longest gaps "
                    + ", ".join(f"{h} {g:.0f} ms" for h, g in gaps.items())
                    + f" (period {period_ms:.0f} ms); interpreter stopped up to "
                    + f"{cycle['interpreter']['longest_stop_ms']:.0f} ms"
                )
                write_results(args.out, out_name, res)  # a run cut short keeps what it measured
            res["after"] = _usage()
        finally:
            pauses.close()
            stream.close()
    print(write_results(args.out, out_name, res))
    return 0
