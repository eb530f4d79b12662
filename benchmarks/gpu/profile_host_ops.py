"""GPU machine: the host cost of each call a thread-mode worker makes per frame, timed one call at a time.

profile_steps.py shows each model spending 0.13-0.26 ms between waking with its input and launching its first graph.
This times the calls in that stretch on an idle engine (thread mode, compiled depth + seg, slot-bound), N calls
each, so the stretch can be attributed: mean microseconds per call, into $OUT/host_ops.json. TINY=1: CPU smoke run.
"""

from __future__ import annotations

import json
import os
import time

import torch

from vpengine.bench.paper import Setup, engines
from vpengine.runtime import worker as worker_mod

out_dir = os.environ.get("OUT", "/tmp/out")
os.makedirs(out_dir, exist_ok=True)
setup = Setup(backend="compile", frames=10, results="borrow")
if os.environ.get("TINY"):
    setup = Setup(
        "cpu", "fp32", 120, 160, "tiny_vit", "tiny_depth", "tiny_seg", "tiny_det", {}, {}, "eager", 10, True
    )
cores: list[worker_mod.WorkerCore] = []
_init = worker_mod.WorkerCore.__init__


def _core_init(self, *a, **kw):  # type: ignore[no-untyped-def]
    _init(self, *a, **kw)
    cores.append(self)


worker_mod.WorkerCore.__init__ = _core_init  # type: ignore[method-assign]
N = 2000


def per_call_us(fn, n: int = N) -> float:  # type: ignore[no-untyped-def]
    fn()
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n * 1e6


def time_core(core: worker_mod.WorkerCore) -> dict[str, float]:
    dev, ex, r = core.dev, core.model, {}

    def acquire_abort() -> None:
        core.writer.abort(core.writer.acquire(timeout=None))

    def stream_ctx() -> None:
        with dev.active():
            pass

    def inference() -> None:
        with torch.inference_mode():
            pass

    r["time.monotonic"] = per_call_us(time.monotonic)
    r["writer.acquire+abort"] = per_call_us(acquire_abort)
    r["dev.active() enter+exit"] = per_call_us(stream_ctx)
    r["torch.inference_mode() enter+exit"] = per_call_us(inference)
    r["control.record_run"] = per_call_us(lambda: core.control.record_run(core.name, 0.0, 0.001, 0.002, 1))
    r["control.heartbeat"] = per_call_us(lambda: core.control.heartbeat(core.name))
    r["gate.update"] = per_call_us(lambda: core.gate.update(core.control.rate(core.name), time.monotonic()))
    stream = dev.stream
    if stream is None:
        return r
    ev = torch.cuda.Event()
    r["stream.wait_event"] = per_call_us(lambda: stream.wait_event(ev))
    r["event.record"] = per_call_us(lambda: ev.record(stream))
    if core._bound:
        with dev.active(), torch.inference_mode():
            for label, g, n in (
                ("in-copy graph replay", ex._in_graphs[0], 500),
                ("model graph replay", ex._graph, 50),
                ("out-copy graph replay", ex._out_graphs[0], 500),
            ):
                dev.complete()
                launches = []
                for _ in range(n):
                    t0 = time.perf_counter()
                    g.replay()
                    launches.append(time.perf_counter() - t0)
                    dev.complete()  # one launch at a time, each on an idle stream, as per frame
                launches.sort()
                r[label] = launches[len(launches) // 2] * 1e6  # median: launches on an idle stream
    return r


report: dict[str, dict[str, float]] = {}
with engines([setup.config([setup.head("depth", "depth"), setup.head("seg", "seg")], mode="thread")]) as (
    eng,
):
    time.sleep(1.0)
    for core in cores:
        report[core.name] = {k: round(v, 2) for k, v in time_core(core).items()}
        print(core.name, report[core.name])
with open(os.path.join(out_dir, "host_ops.json"), "w") as f:
    json.dump(report, f, indent=1)
