"""GPU machine: Note [Result hand-off], its variants alternated on one engine, round after round, so that machine
noise falls on every variant alike. Thread mode, compiled depth + seg, frames written in place (``frame_slot``),
borrowed results, one frame in flight, as the floor experiment runs it:

* event: the heads publish queued results with an event; the caller sleeps in the driver until the result is
  there (the default);
* event, wait spin 200 us: the same, the caller sleeping through the predicted part of each wait and polling the
  event for the last 200 us, then up to 200 us past the predicted end before it sleeps in the driver after all
  (``runtime.wait_spin_us: 200``);
* event, driver spin 200 us: the spin as it was before the poll: the slots' events made with default flags, the
  caller sleeping through the predicted part and then spinning in the driver until the result is there, however
  late;
* event, poll holding the lock / event, poll with sleep(0): diagnostics of the poll: never offering the
  interpreter lock between queries, or offering it with ``time.sleep(0)`` (as first written) instead of
  ``os.sched_yield()``;
* host: the heads wait for their work on the host, then publish (``runtime.result_handoff: host``);
* event, caller spins: diagnostic, not an option: default-flag events and no sleep: the caller spins in the driver
  for the whole wait, the least wake-up there is;
* ... | borrow after wait: each borrowed result borrowed only after its wait for the device, not all before any
  wait (as before);
* ..., publish first: the submitting thread publishes the frame, then pins it for the foundation and queues its work
  (Note [Inline launch] before its work was queued ahead of the publish).

VARIANTS (separated by ";") picks which; the " | " modifiers go with any of them. PRIORITIES (``--stream-priorities`` syntax, e.g. depth=-1) starts a second
engine with those stream priorities and runs every variant on both, the second's names suffixed with
``[PRIORITIES]``.

ROUNDS rounds (default 8) of FRAMES frames (default 200) per variant; HEADS as in profile_steps.py
(default depth,seg; depth:8 for E1's eight depth heads); SEG_BLOCK=PIXELS,WARPS sets the seg head's fused kernel's
programs (default 128,2). Writes ``ab_result_handoff{TAG}.json`` under $OUT: each
round's p50, mean and the caller's CPU time per frame (its thread's: a spin in the driver counts) per variant, and
each variant's median of those, and how many spinning waits caught their result and how many were left to the
driver. Set TINY=1 for a CPU smoke run.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import statistics
import time

import torch

from vpengine.bench.common import machine_info
from vpengine.bench.paper import Setup, engines, frames, lockstep, parse_priorities
from vpengine.engine import Engine
from vpengine.runtime import worker as worker_mod
from vpengine.transport import ring as ring_mod

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
if os.environ.get("SEG_BLOCK"):  # the seg head's fused kernel's pixels per program and warps, e.g. 512,8
    from vpengine.models import _triton_upsample_argmax as seg_kernel

    block, warps = (int(v) for v in os.environ["SEG_BLOCK"].split(","))
    seg_kernel.BLOCK, seg_kernel.NUM_WARPS = block, warps

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


def _poll_in_driver(event, slot, predicted_s, spin_s):  # type: ignore[no-untyped-def]
    """The wait spin as it was: sleep until ``spin_s`` before the predicted end, then leave the rest to
    ``synchronize`` (which spins in the driver on default-flag events, unbounded)."""
    ahead = slot.t_publish + predicted_s - spin_s - time.monotonic()
    if ahead > 0:
        time.sleep(ahead)
    return False


def _copy_out_late(self, pinned, copy=True):  # type: ignore[no-untyped-def]
    """Engine._copy_out as it was: each result borrowed only after its wait for the device."""
    out = {}
    for h, s in pinned:
        self._results_readers[h].ring.wait_done(s, self.config.runtime.wait_spin_us * 1e-6)
        out[h] = self._to_result(h, s, None if copy else self._borrow(h, s))
    return out


_copy_out = Engine._copy_out
_poll = ring_mod._poll
POLLS = {  # variant -> (how the wait spins, whether the slots' events have default flags)
    "event, wait spin 200 us": (_poll, False),
    "event, driver spin 200 us": (_poll_in_driver, True),
    # diagnostics: never offering the interpreter lock between polls; offering it as first written
    "event, poll holding the lock": (functools.partial(_poll, offer=lambda: None), False),
    "event, poll with sleep(0)": (functools.partial(_poll, offer=lambda: time.sleep(0)), False),
}


class Arm:
    """One engine under test and its heads' two sets of result events."""

    def __init__(self, eng, label: str, head_cores) -> None:  # type: ignore[no-untyped-def]
        self.eng, self.label, self.head_cores = eng, label, head_cores
        self.blocking = {c.name: c._handoff for c in head_cores}
        self.by_event = all(v is not None for v in self.blocking.values())
        self.spinning = (
            {c.name: [torch.cuda.Event() for _ in ev] for c, ev in zip(head_cores, self.blocking.values())}
            if self.by_event and torch.cuda.is_available()
            else {}
        )

    def variant(self, name: str) -> None:
        """Set the engine up for ``name`` (between frames: no work in flight)."""
        full = name
        name, *mods = name.split(" | ")
        worker_mod.InlineLaunch.publish = _publish_first if name.endswith("publish first") else _queue_first  # type: ignore[method-assign]
        Engine._copy_out = _copy_out_late if "borrow after wait" in mods else _copy_out  # type: ignore[method-assign]
        base = name.removesuffix(", publish first")
        poll, default_flags = POLLS.get(base, (_poll, base == "event, caller spins"))
        self.eng.config.runtime.wait_spin_us = SPIN_US if base in POLLS else 0.0
        tally = fallbacks.setdefault(full + self.label, [0, 0])

        def counted(*a):  # type: ignore[no-untyped-def]
            caught = poll(*a)
            tally[0 if caught else 1] += 1
            return caught

        ring_mod._poll = counted
        for c in self.head_cores:
            events = (
                None if base == "host" else self.spinning[c.name] if default_flags else self.blocking[c.name]
            )
            c._handoff = c.writer.ring.device_events = events


report: dict[str, object] = {"machine": machine_info(), "frames": setup.frames, "rounds": rounds}
priorities = os.environ.get("PRIORITIES", "")
cfgs = [setup.config(heads, mode="thread")]
# a second engine, its streams' priorities set (--stream-priorities syntax): the same variants on each
if priorities:
    prioritised = dataclasses.replace(setup, stream_priorities=parse_priorities(priorities))
    cfgs.append(prioritised.config(heads, mode="thread"))
report["priorities"] = priorities
# variant -> [waits whose spin caught the result, waits left to the driver]
fallbacks: dict[str, list[int]] = {}
with engines(cfgs) as started:
    arms = []
    for i, eng in enumerate(started):
        ctl = eng._res.control
        own = [c for c in cores if c.control is ctl and c.name != "foundation"]
        arms.append(Arm(eng, "" if i == 0 else f" [{priorities}]", own))
    names = ["event", "host"]
    report["handed_off_by_event"] = arms[0].by_event
    if arms[0].spinning:
        names += [*POLLS, "event, caller spins"]
    names += [n + ", publish first" for n in ("event", "host", "event, wait spin 200 us")]
    chosen = [n for n in os.environ.get("VARIANTS", "").split(";") if n]
    names = [n for n in chosen if n.split(" | ")[0] in names] if chosen else names
    runs = [(a, n) for a in arms for n in names]
    for a in arms:
        for i in range(30):
            a.eng.wait(a.eng.submit(imgs[i % len(imgs)]), timeout=60)
    rows: dict[str, list[dict[str, float]]] = {n + a.label: [] for a, n in runs}
    for r in range(rounds):
        for a, n in runs:
            a.variant(n)
            cpu = time.thread_time()  # this (the caller's) thread only: a spin in the driver counts here
            row = lockstep(a.eng, imgs, setup, slot=True)
            row["caller_cpu_ms_per_frame"] = (time.thread_time() - cpu) * 1e3 / (setup.frames + 10)
            rows[n + a.label].append(row)
        print(
            f"round {r + 1}/{rounds}: " + ", ".join(f"{k} {v[-1]['p50']:.3f}" for k, v in rows.items()),
            flush=True,
        )
    for a in arms:
        a.variant("event")
summary = {
    n: {
        "median_p50_ms": statistics.median(x["p50"] for x in rows[n]),
        "median_mean_ms": statistics.median(x["mean"] for x in rows[n]),
        "median_p99_ms": statistics.median(x["p99"] for x in rows[n]),
        "median_caller_cpu_ms_per_frame": statistics.median(x["caller_cpu_ms_per_frame"] for x in rows[n]),
        "rounds_p50_ms": [round(x["p50"], 4) for x in rows[n]],
        "rounds_mean_ms": [round(x["mean"], 4) for x in rows[n]],
        "spins_caught_left_to_driver": fallbacks.get(n, [0, 0]),
    }
    for n in rows
}
report["variants"] = summary
for n, s in summary.items():
    print(
        f"{n}: median p50 {s['median_p50_ms']:.3f} ms, p99 {s['median_p99_ms']:.3f} ms, median mean "
        f"{s['median_mean_ms']:.3f} ms, caller CPU {s['median_caller_cpu_ms_per_frame']:.3f} ms a frame, spins "
        f"caught / left to the driver {s['spins_caught_left_to_driver']}"
    )
with open(os.path.join(out_dir, f"ab_result_handoff{os.environ.get('TAG', '')}.json"), "w") as f:
    json.dump(report, f, indent=1)
