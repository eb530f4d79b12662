"""GPU machine: where one frame's time goes in thread mode, stage by stage, and what the host-side knobs change.

Thread mode runs every worker in this process, so the worker loop can be timed from outside: ``WorkerCore._step``
is wrapped to stamp (time.monotonic) each stage of each model's run on each frame -- input published, pinned (woken),
model enqueued, output copies enqueued, device work complete, output published -- and the caller stamps submit and
the moment ``wait`` returns. The mean of each stage over the frames is the waterfall. Variants, on one engine:

* submit: ``Engine.submit`` (the frame copied into the input slot), latency from the call;
* slot: ``Engine.frame_slot`` (the frame written in place), latency from the end of the write; the foundation hands
  its features to the heads by CUDA event (Note [Event hand-off]): its ``copies_enqueued`` and ``device_done`` come
  after the heads' ``input_published``; when it is slot-bound, the thread that closes the frame slot queues its work
  (Note [Inline launch]) before it publishes it: its ``pinned`` is then when that began (before
  ``input_published``), and ``finish_started`` when its worker took over;
* slot worker launch: the same on an engine of its own with ``runtime.inline_launch: never`` (run first);
* slot host hand-off: the foundation waits for its work on the host before it publishes (as before that Note);
* slot results on host: each head waits for its work on the host before it publishes its results (as before Note
  [Result hand-off]; with it, a head's ``published`` comes before its ``copies_enqueued`` and ``device_done``);
* slot unbound: compiled models called with the slots' tensors and their outputs copied by the worker, one copy per
  tensor (as before Note [Slot-bound runs]), instead of running from graphs bound to the slots;
* slot+spin200 / slot+spin100: ``runtime.sync_spin_us`` 200 / 100 (sleep through the predicted device time, spin
  in the driver for the rest; Note [Device sync]);
* slot+fullspin: device sync by spinning on the event the whole time (cudaEventDefault): the least wake-up latency
  there is, at a core per worker. Diagnostic only: not something the engine does;
* slot+switch: ``sys.setswitchinterval(1e-4)`` (CPython's default is 5 ms: a thread waiting for the interpreter
  lock asks the holder to drop it only after that long).

A run's launch is stamped after its stream waited on the features' event (a head, ``waited_on_event``), on entering
a stream context (``active_called``, ``stream_entered``: a launch from another thread that cannot launch raw) and
before its first launch (``run_bound_called``); a slot-bound model's after each of its three graph launches: ``in_copy_enqueued`` (the input slot
copied into the graph's static input), ``graph_enqueued`` (the model) and ``model_enqueued`` (the copy into the
output slot). VARIANTS (comma-separated names from the list above) picks which run; default: all. PRIORITIES
(``--stream-priorities`` of ``vpengine bench paper``, e.g. depth=-1) sets the models' stream priorities.

Then a torch.profiler trace of a few frames (chrome trace, gzipped) for the device timeline. Set TINY=1 for a CPU
smoke run of the script.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gzip
import json
import os
import shutil
import sys
import time
from collections import defaultdict

import numpy as np
import torch

from vpengine.bench.common import machine_info
from vpengine.bench.paper import Setup, engines, frames, parse_priorities
from vpengine.runtime import worker as worker_mod
from vpengine.runtime.device import DeviceContext

out_dir = os.environ.get("OUT", "/tmp/out")
os.makedirs(out_dir, exist_ok=True)
setup = Setup(
    backend=os.environ.get("BACKEND", "compile"), frames=300, results=os.environ.get("RESULTS", "borrow")
)
if os.environ.get("TINY"):
    setup = Setup(
        "cpu", "fp32", 120, 160, "tiny_vit", "tiny_depth", "tiny_seg", "tiny_det", {}, {}, "eager", 50, True
    )
    setup.results = "borrow"
setup.stream_priorities = parse_priorities(os.environ.get("PRIORITIES", ""))  # e.g. depth=-1
kinds = os.environ.get("HEADS", "depth,seg").split(
    ","
)  # "kind" or "kind:count" (depth:8 is E1's 8 depth heads)
heads = []
for spec in kinds:
    kind, _, count = spec.partition(":")
    heads += [setup.head(kind, f"{kind}{i}" if count else kind) for i in range(int(count or 1))]
imgs = frames(setup)

stamps: dict[str, dict[int, dict[str, float]]] = defaultdict(dict)  # model -> frame id -> stage -> time
cores: list[worker_mod.WorkerCore] = []
devices: list[DeviceContext] = []
_plain_launch = worker_mod.WorkerCore._launch
_plain_finish = worker_mod.WorkerCore._finish
_plain_core_init = worker_mod.WorkerCore.__init__
_plain_dev_init = DeviceContext.__init__


def _core_init(self, *a, **kw):  # type: ignore[no-untyped-def]
    _plain_core_init(self, *a, **kw)
    cores.append(self)


def _dev_init(self, *a, **kw):  # type: ignore[no-untyped-def]
    _plain_dev_init(self, *a, **kw)
    devices.append(self)


class _Stamped:
    """The executor, stamping when its work is enqueued."""

    def __init__(self, ex, rec):  # type: ignore[no-untyped-def]
        self.ex, self.rec = ex, rec

    def __call__(self, inputs):  # type: ignore[no-untyped-def]
        out = self.ex(inputs)
        self.rec["model_enqueued"] = time.monotonic()
        return out

    def run_bound(self, i, j):  # type: ignore[no-untyped-def]
        ex, rec = self.ex, self.rec
        rec["run_bound_called"] = time.monotonic()  # inside the stream context and inference mode
        ex._in_graphs[i].replay()  # CompiledExecutor.run_bound, one launch at a time
        rec["in_copy_enqueued"] = time.monotonic()
        ex._graph.replay()
        rec["graph_enqueued"] = time.monotonic()
        ex._out_graphs[j].replay()
        rec["model_enqueued"] = time.monotonic()

    def run_bound_on(self, stream, i, j):  # type: ignore[no-untyped-def]
        ex, rec = self.ex, self.rec  # CompiledExecutor.run_bound_on, one launch at a time
        raw = ex._raw
        if raw is None or stream is None or torch.cuda.current_device() != raw.device_index:
            with torch.cuda.stream(stream):
                rec["stream_entered"] = time.monotonic()
                self.run_bound(i, j)
            return
        rec["run_bound_called"] = time.monotonic()
        launch, s = raw.cudart.cudaGraphLaunch, stream.cuda_stream
        for h, stage in (
            (raw.ins[i], "in_copy_enqueued"),
            (raw.model, "graph_enqueued"),
            (raw.outs[j], "model_enqueued"),
        ):
            launch(h, s)
            rec[stage] = time.monotonic()


def _stamped_launch(self, slot, out):  # type: ignore[no-untyped-def]
    # in the submitting thread when it launches the foundation (Note [Inline launch]): its "pinned" is then when
    # that thread began queueing, and its "finish_started" when the worker thread took over
    # launched before the frame is published (by the submitting thread): keyed -1 until _stamped_finish knows it
    rec = {"input_published": slot.t_publish, "pinned": time.monotonic()}
    stamps[self.name][slot.frame_id] = rec
    model, dev = self.model, self.dev
    plain_active, plain_wait_on = dev.active, dev.wait_on

    @contextlib.contextmanager
    def active():  # type: ignore[no-untyped-def]
        rec["active_called"] = time.monotonic()
        with plain_active():
            rec["stream_entered"] = time.monotonic()
            yield

    def wait_on(event):  # type: ignore[no-untyped-def]
        plain_wait_on(event)
        rec["waited_on_event"] = time.monotonic()

    self.model = _Stamped(model, rec)
    dev.active, dev.wait_on = active, wait_on
    try:
        _plain_launch(self, slot, out)
    finally:
        self.model = model
        del dev.active, dev.wait_on


def _stamped_finish(self, slot, out, t_start):  # type: ignore[no-untyped-def]
    early = stamps[self.name].pop(-1, None)
    if early is not None:  # launched before it was published: its times are known now
        early["input_published"] = slot.t_publish
        stamps[self.name][slot.frame_id] = early
    rec = stamps[self.name].setdefault(slot.frame_id, {})
    rec["finish_started"] = time.monotonic()
    dev = self.dev
    plain_complete = dev.complete

    def complete():  # type: ignore[no-untyped-def]
        rec["copies_enqueued"] = time.monotonic()
        plain_complete()
        rec["device_done"] = time.monotonic()

    dev.complete = complete
    try:
        _plain_finish(self, slot, out, t_start)
    finally:
        del dev.complete
    rec["published"] = out.t_publish  # set by the publish, before or after the device work is done
    rec["finished"] = time.monotonic()


def _fullspin_complete(self):  # type: ignore[no-untyped-def]
    if self.stream is not None:
        ev = getattr(self, "_spin_event", None)
        if ev is None:
            ev = self._spin_event = torch.cuda.Event()  # default flags: synchronize() spins
        ev.record(self.stream)
        ev.synchronize()


def run_variant(eng, variant: str, n: int) -> dict[str, object]:  # type: ignore[no-untyped-def]
    stamps.clear()
    caller: dict[int, dict[str, float]] = {}
    slot = variant != "submit"
    for i in range(n + 10):
        img = imgs[i % len(imgs)]
        if slot:
            with eng.frame_slot() as s:
                np.copyto(s.array, img)
                t0 = time.monotonic()
            fid = s.frame_id
        else:
            t0 = time.monotonic()
            fid = eng.submit(img)
        t_sub = time.monotonic()
        eng.wait(fid, timeout=60, copy=setup.copy)
        if i >= 10:
            caller[fid] = {"start": t0, "submitted": t_sub, "returned": time.monotonic()}
    rows: dict[str, list[float]] = defaultdict(list)
    for fid, c in caller.items():
        t0 = c["start"]
        rows["caller.submitted"].append(c["submitted"] - t0)
        rows["caller.returned"].append(c["returned"] - t0)
        for model, per in stamps.items():
            rec = per.get(fid)
            if rec is None:
                continue
            for stage, t in rec.items():
                rows[f"{model}.{stage}"].append(t - t0)
    table = {k: round(float(np.mean(v)) * 1e3, 4) for k, v in rows.items()}
    lat = np.array(rows["caller.returned"]) * 1e3
    summary = {
        "mean_ms": float(lat.mean()),
        "p50_ms": float(np.median(lat)),
        "p99_ms": float(np.percentile(lat, 99)),
        "stages_ms_from_start": dict(sorted(table.items(), key=lambda kv: kv[1])),
    }
    print(
        variant, f"mean {summary['mean_ms']:.3f} ms p50 {summary['p50_ms']:.3f} p99 {summary['p99_ms']:.3f}"
    )
    for k, v in summary["stages_ms_from_start"].items():
        print(f"   {v:8.3f}  {k}")
    return summary


report: dict[str, object] = {
    "machine": machine_info(),
    "setup": {
        "heads": kinds,
        "backend": setup.backend,
        "results": setup.results,
        "stream_priorities": setup.stream_priorities,
    },
}
worker_mod.WorkerCore._launch = _stamped_launch  # type: ignore[method-assign]
worker_mod.WorkerCore._finish = _stamped_finish  # type: ignore[method-assign]
worker_mod.WorkerCore.__init__ = _core_init  # type: ignore[method-assign]
DeviceContext.__init__ = _dev_init  # type: ignore[method-assign]
switch = sys.getswitchinterval()
blocking_complete = DeviceContext.complete


def spin(us: float) -> None:
    for d in devices:
        d.set_spin(us * 1e-6)


chosen = set(filter(None, os.environ.get("VARIANTS", "").split(",")))


def want(v: str) -> bool:
    return not chosen or v in chosen


if want("slot worker launch"):  # its own engine first: inline launch is an engine setting
    with engines([dataclasses.replace(setup, inline_launch="never").config(heads, mode="thread")]) as (eng,):
        for i in range(30):
            eng.wait(eng.submit(imgs[i % len(imgs)]), timeout=60)
        report["slot worker launch"] = run_variant(eng, "slot worker launch", setup.frames)
    cores.clear()
    devices.clear()

with engines([setup.config(heads, mode="thread")]) as (eng,):
    report["bound"] = {c.name: c._bound for c in cores}
    inline = eng._res.rings["input"].inline
    report["inline_launch"] = inline is not None
    print("slot-bound:", report["bound"], "inline launch:", report["inline_launch"])
    for i in range(30):
        eng.wait(eng.submit(imgs[i % len(imgs)]), timeout=60)

    if want("submit"):
        report["submit"] = run_variant(eng, "submit", setup.frames)
    report["slot"] = run_variant(eng, "slot", setup.frames)
    fm = next(c for c in cores if c.name == "foundation")
    handoff = fm._handoff
    report["handoff"] = handoff is not None
    if want("slot host hand-off"):
        fm._handoff = fm.writer.ring.device_events = None  # between frames: none in flight
        report["slot host hand-off"] = run_variant(eng, "slot host hand-off", setup.frames)
        fm._handoff = fm.writer.ring.device_events = handoff
    if want("slot results on host"):
        head_cores = [c for c in cores if c.name != "foundation"]
        saved = {c: c._handoff for c in head_cores}
        for c in head_cores:  # between frames: none in flight
            c._handoff = c.writer.ring.device_events = None
        report["slot results on host"] = run_variant(eng, "slot results on host", setup.frames)
        for c, events in saved.items():
            c._handoff = c.writer.ring.device_events = events
    if want("slot unbound"):
        bound = {c: c._bound for c in cores}
        for c in cores:
            c._bound = False
        report["slot unbound"] = run_variant(eng, "slot unbound", setup.frames)
        for c, b in bound.items():
            c._bound = b
    for us in (200, 100):
        if want(f"slot+spin{us}"):
            spin(us)
            run_variant(eng, "(learning)", 50)
            report[f"slot+spin{us}"] = run_variant(eng, f"slot+spin{us}", setup.frames)
    spin(0)
    if torch.cuda.is_available() and want("slot+fullspin"):
        DeviceContext.complete = _fullspin_complete  # type: ignore[method-assign]
        report["slot+fullspin"] = run_variant(eng, "slot+fullspin", setup.frames)
        DeviceContext.complete = blocking_complete  # type: ignore[method-assign]
    if want("slot+switch"):
        sys.setswitchinterval(1e-4)
        report["slot+switch"] = run_variant(eng, "slot+switch", setup.frames)
        sys.setswitchinterval(switch)
    report["slot_again"] = run_variant(eng, "slot", setup.frames)
    # the device timeline of a few frames
    worker_mod.WorkerCore._launch = _plain_launch  # type: ignore[method-assign]
    worker_mod.WorkerCore._finish = _plain_finish  # type: ignore[method-assign]
    acts = [torch.profiler.ProfilerActivity.CPU]
    if torch.cuda.is_available():
        acts.append(torch.profiler.ProfilerActivity.CUDA)
    with torch.profiler.profile(activities=acts) as prof:
        for i in range(20):
            with eng.frame_slot() as s, torch.profiler.record_function("write frame"):
                np.copyto(s.array, imgs[i % len(imgs)])
            with torch.profiler.record_function("wait"):
                eng.wait(s.frame_id, timeout=60, copy=setup.copy)
    trace = os.path.join(out_dir, "profile_steps_trace.json")
    prof.export_chrome_trace(trace)
    with open(trace, "rb") as f, gzip.open(trace + ".gz", "wb") as g:
        shutil.copyfileobj(f, g)
    os.remove(trace)
    report["profiler_top"] = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25)
    print(report["profiler_top"])
with open(os.path.join(out_dir, f"profile_steps{os.environ.get('TAG', '')}.json"), "w") as f:
    json.dump(report, f, indent=1)
