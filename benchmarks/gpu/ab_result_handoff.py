"""GPU machine: Note [Result hand-off], its variants alternated on one engine, round after round, so that machine
noise falls on every variant alike. Thread mode, compiled depth + seg, frames written in place (``frame_slot``),
borrowed results, one frame in flight, as the floor experiment runs it:

* event: the heads publish queued results with an event; the caller sleeps in the driver until the result is
  there (the default);
* event, wait spin 200 us: the same with the slots' events made with default flags, and the caller sleeping through
  the predicted part of each wait and spinning in the driver for the last 200 us (``runtime.wait_spin_us: 200``);
* host: the heads wait for their work on the host, then publish (``runtime.result_handoff: host``);
* event, caller spins: diagnostic, not an option: default-flag events and no sleep: the caller spins in the driver
  for the whole wait, the least wake-up there is;
* ..., publish first: the submitting thread publishes the frame, then pins it for the foundation and queues its work
  (Note [Inline launch] before its work was queued ahead of the publish).

VARIANTS (separated by ";") picks which.

ROUNDS rounds (default 8) of FRAMES frames (default 200) per variant; HEADS as in profile_steps.py
(default depth,seg; depth:8 for E1's eight depth heads). Writes ``ab_result_handoff{TAG}.json`` under $OUT: each
round's p50, mean and the caller's CPU time per frame (its thread's: a spin in the driver counts) per variant, and
each variant's median of those. Set TINY=1 for a CPU smoke run.
"""

from __future__ import annotations

import json
import os
import statistics
import time

import torch

from vpengine.bench.common import machine_info
from vpengine.bench.paper import Setup, engines, frames, lockstep
from vpengine.runtime import worker as worker_mod

out_dir = os.environ.get("OUT", "/tmp/out")
os.makedirs(out_dir, exist_ok=True)
rounds = int(os.environ.get("ROUNDS", "8"))
setup = Setup(backend="compile", frames=int(os.environ.get("FRAMES", "200")), results="borrow")
if os.environ.get("TINY"):
    setup = Setup(
        "cpu", "fp32", 120, 160, "tiny_vit", "tiny_depth", "tiny_seg", "tiny_det", {}, {}, "eager", 20, True
    )
    setup.results = "borrow"
heads = []
for spec in os.environ.get("HEADS", "depth,seg").split(","):  # "kind" or "kind:count" (depth:8: E1's eight)
    kind, _, count = spec.partition(":")
    heads += [setup.head(kind, f"{kind}{i}" if count else kind) for i in range(int(count or 1))]
imgs = frames(setup)

cores: list[worker_mod.WorkerCore] = []
_plain_init = worker_mod.WorkerCore.__init__


def _init(self, *a, **kw):  # type: ignore[no-untyped-def]
    _plain_init(self, *a, **kw)
    cores.append(self)


worker_mod.WorkerCore.__init__ = _init  # type: ignore[method-assign]
SPIN_US = 200.0


_queue_first = worker_mod.InlineLaunch.publish


def _publish_first(self, writer, slot, frame_id, t_capture, t_submit):  # type: ignore[no-untyped-def]
    seq = writer.publish(slot, frame_id, t_capture, t_submit)
    with self.cond:
        core, out = self._core, self._out
        if core is None or out is None or core.control.rate(core.name) != self._rate:
            return seq
        pinned = core.reader.pin(timeout=0)
        self._core = self._out = None
        t_start, error = time.monotonic(), None
        try:
            core._launch(pinned, out)
        except Exception as e:
            error = e
        self._done = (pinned, t_start, error)
        self.launches += 1
        self.cond.notify_all()
        return seq


def variant(name: str) -> None:
    """Set the engine up for ``name`` (between frames: no work in flight)."""
    worker_mod.InlineLaunch.publish = _publish_first if name.endswith("publish first") else _queue_first  # type: ignore[method-assign]
    base = name.removesuffix(", publish first")
    eng.config.runtime.wait_spin_us = SPIN_US if base == "event, wait spin 200 us" else 0.0
    for c in head_cores:
        events = None if base == "host" else blocking[c.name] if base == "event" else spinning[c.name]
        c._handoff = c.writer.ring.device_events = events


names = ["event", "host"]
report: dict[str, object] = {"machine": machine_info(), "frames": setup.frames, "rounds": rounds}
with engines([setup.config(heads, mode="thread")]) as (eng,):
    head_cores = [c for c in cores if c.name != "foundation"]
    blocking = {c.name: c._handoff for c in head_cores}
    report["handed_off_by_event"] = all(v is not None for v in blocking.values())
    if report["handed_off_by_event"] and torch.cuda.is_available():
        names += ["event, wait spin 200 us", "event, caller spins"]
        spinning = {c.name: [torch.cuda.Event() for _ in ev] for c, ev in zip(head_cores, blocking.values())}
    names += [n + ", publish first" for n in names if n != "event, caller spins"]
    chosen = [n for n in os.environ.get("VARIANTS", "").split(";") if n]
    names = [n for n in names if not chosen or n in chosen]
    for i in range(30):
        eng.wait(eng.submit(imgs[i % len(imgs)]), timeout=60)
    rows: dict[str, list[dict[str, float]]] = {n: [] for n in names}
    for r in range(rounds):
        for n in names:
            variant(n)
            cpu = time.thread_time()  # this (the caller's) thread only: a spin in the driver counts here
            rows[n].append(lockstep(eng, imgs, setup, slot=True))
            rows[n][-1]["caller_cpu_ms_per_frame"] = (time.thread_time() - cpu) * 1e3 / (setup.frames + 10)
        print(
            f"round {r + 1}/{rounds}: " + ", ".join(f"{n} {rows[n][-1]['p50']:.3f}" for n in names),
            flush=True,
        )
    variant("event")
summary = {
    n: {
        "median_p50_ms": statistics.median(x["p50"] for x in rows[n]),
        "median_mean_ms": statistics.median(x["mean"] for x in rows[n]),
        "median_caller_cpu_ms_per_frame": statistics.median(x["caller_cpu_ms_per_frame"] for x in rows[n]),
        "rounds_p50_ms": [round(x["p50"], 4) for x in rows[n]],
        "rounds_mean_ms": [round(x["mean"], 4) for x in rows[n]],
    }
    for n in names
}
report["variants"] = summary
for n, s in summary.items():
    print(
        f"{n}: median p50 {s['median_p50_ms']:.3f} ms, median mean {s['median_mean_ms']:.3f} ms, "
        f"caller CPU {s['median_caller_cpu_ms_per_frame']:.3f} ms a frame"
    )
with open(os.path.join(out_dir, f"ab_result_handoff{os.environ.get('TAG', '')}.json"), "w") as f:
    json.dump(report, f, indent=1)
