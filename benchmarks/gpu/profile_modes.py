"""GPU machine: where the engine's time goes over the device-time floor, thread vs process mode.

Runs the floor's models (compiled backbone + depth + seg at 1080p) in lockstep, prints per-model latencies from the
control block (run time, and submit -> model done) and the time the caller spends copying results out of the
mailboxes, and samples the process with py-spy when present. HEADS picks other heads: "depth:8" is E1's 8 depth heads,
"det:8" E2's 8 detection heads (DET picks the recipe); MPS=required runs every process on a CUDA MPS daemon (found, or
started for the run and stopped after); RESULTS=borrow takes results as borrowed views (Engine.wait(copy=False)).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np

from vpengine.bench.paper import Setup, _mps_daemon, engines, frames

out_dir = os.environ.get("OUT", "/tmp/out")
setup = Setup(
    backend=os.environ.get("BACKEND", "compile"),
    frames=300,
    det=os.environ.get("DET", "frcnn_dinov2_lite"),
    mps=os.environ.get("MPS", "off"),
    results=os.environ.get("RESULTS", "copy"),
)
if os.environ.get("TINY"):  # a CPU smoke run of this script
    setup = Setup(
        "cpu", "fp32", 120, 160, "tiny_vit", "tiny_depth", "tiny_seg", "tiny_det", {}, {}, "eager", 50, True
    )
heads = []
for spec in os.environ.get("HEADS", "depth,seg").split(","):  # "kind" or "kind:count"
    kind, _, count = spec.partition(":")
    names = [f"{kind}{i}" for i in range(int(count))] if count else [kind]
    heads += [setup.head(kind, name) for name in names]
imgs = frames(setup)
report: dict[str, object] = {"mps": setup.mps, "results": setup.results}
stack = contextlib.ExitStack()
if setup.mps == "required":
    setup.mps_pipe_directory = stack.enter_context(_mps_daemon())
for mode in sys.argv[1:] or ["thread", "process"]:
    with engines([setup.config(heads, mode=mode)]) as (eng,):
        for i in range(30):
            eng.wait(eng.submit(imgs[i % len(imgs)]), timeout=60)
        spy = None
        if shutil.which("py-spy"):
            spy = subprocess.Popen(
                [
                    "py-spy",
                    "record",
                    "--pid",
                    str(os.getpid()),
                    "--duration",
                    "4",
                    "--rate",
                    "1000",
                    "--threads",
                    "--idle",
                    "--format",
                    "raw",
                    "-o",
                    f"{out_dir}/pyspy_{mode}.txt",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.STDOUT,
            )
        copy: list[float] = []
        plain_copy_out = eng._copy_out

        def timed_copy_out(pinned, copy_results=True, _f=plain_copy_out, _c=copy):
            t = time.perf_counter()
            try:
                return _f(pinned, copy_results)
            finally:
                _c.append(time.perf_counter() - t)

        eng._copy_out = timed_copy_out
        lat, sub, wait = [], [], []
        for i in range(setup.frames):
            t0 = time.perf_counter()
            fid = eng.submit(imgs[i % len(imgs)])
            t1 = time.perf_counter()
            eng.wait(fid, timeout=60, copy=setup.copy)
            t2 = time.perf_counter()
            lat.append(t2 - t0), sub.append(t1 - t0), wait.append(t2 - t1)
        if spy:
            spy.wait(30)
        st = eng.stats()["models"]
        row = {
            "lockstep_ms": float(np.mean(lat) * 1e3),
            "submit_ms": float(np.mean(sub) * 1e3),
            "wait_ms": float(np.mean(wait) * 1e3),
            "copy_out_ms_per_frame": float(np.sum(copy) * 1e3 / setup.frames),
            "models": {
                n: {"run_ms": m["latency_ms"]["mean"], "submit_to_done_ms": m["e2e_latency_ms"]["mean"]}
                for n, m in st.items()
            },
        }
        report[mode] = row
        print(mode, json.dumps(row), flush=True)
stack.close()
with open(f"{out_dir}/profile_modes{os.environ.get('TAG', '')}.json", "w") as f:
    json.dump(report, f, indent=1)
