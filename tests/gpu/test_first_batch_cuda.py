"""Note [First batch] (runtime/worker.py) on CUDA: the first batch of several cameras a stream sends runs nothing for
the first time. What a first launch costs shows as host page faults in the thread that launches it (the driver maps
and fills the kernel's module: some 4,000 in the foundation's thread with 8 cameras on an H200), so the foundation's
thread takes next to none over the stream's first tick. In a fresh process: a module loaded by an earlier test
would hide the cost. Run on the GPU machine: ``pytest -m gpu tests/gpu``."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = [pytest.mark.gpu, pytest.mark.timeout(600), pytest.mark.usefixtures("require_cuda")]

SCRIPT = r"""
import json, sys, threading, time
sys.path[:0] = sys.argv[1:]
from helpers.frames import frame
from tests_paths import tiny
from vpengine.bench.common import proc_stat
from vpengine.engine import Engine

CAMERAS = ["a", "b", "c", "d"]

def faults(name):
    (t,) = [t for t in threading.enumerate() if t.name == name]
    return int(proc_stat(f"/proc/self/task/{t.native_id}/stat")[7])  # minflt

# the backbone, depth and seg compiled: a frame alone runs the graphs bound to its slots, none of the worker's copies
COMPILED = ["foundation_model.backend=compile", "heads.depth.backend=compile", "heads.seg.backend=compile"]
cfg = tiny("thread", "device=cuda", *COMPILED, "cameras=[" + ", ".join("{name: %s}" % c for c in CAMERAS) + "]")
with Engine(cfg) as e:
    sent = []  # when the last camera's frames were submitted
    for r in range(3):  # one frame at a time, 20 ms apart: each camera's spacing is known, its frames run alone
        for i, c in enumerate(CAMERAS):
            sent.append(time.monotonic())
            e.wait(e.submit(frame(4 * r + i), camera=c), timeout=60)
            time.sleep(0.02)
    # until the last camera's next frame is due: every camera's is, and each still delivers (a frame within three
    # of its spacings), so the tick's frames run as one batch
    time.sleep(max(0.0, 2 * sent[-1] - sent[-5] - time.monotonic()))
    before = faults("vpengine-foundation")
    ids = [e.submit(frame(20 + i), camera=c) for i, c in enumerate(CAMERAS)]
    outs = [e.wait(f, timeout=60) for f in ids]
    after = faults("vpengine-foundation")
    print(json.dumps({"faults": after - before, "batched": e.stats()["models"]["foundation"]["batched"],
                      "heads": [sorted(o) for o in outs]}))
"""


def test_the_first_batch_of_several_cameras_loads_nothing_in_the_foundations_thread():
    from pathlib import Path

    from vpengine.runtime.process import package_env

    tests = Path(__file__).resolve().parents[1]
    env = {**package_env(), "TORCHINDUCTOR_COMPILE_THREADS": "1"}  # no compile pool outliving the run
    run = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(tests)], capture_output=True, text=True, env=env, timeout=500
    )
    assert run.returncode == 0, run.stderr[-3000:]
    got = json.loads(run.stdout.strip().splitlines()[-1])
    assert got["batched"] == 4, got  # the tick ran as one batch, and only the tick
    assert all(h == ["depth", "det", "seg"] for h in got["heads"]), got
    assert got["faults"] < 256, got  # 1 MiB of pages; a module loaded here is thousands
