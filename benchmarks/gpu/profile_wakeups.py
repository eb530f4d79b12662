"""GPU machine: what a frame's host hops cost when the thread doing them was idle, step by step.

profile_steps.py found 0.11 ms between a model's run starting and its first graph launch in the real engine, where
the same calls take 25 us in a loop (host_ops.json), and the caller's result 0.17-0.27 ms after the last head
published. Two questions, measured here with nothing else running:

* cold: a CUDA graph launch as a worker does it (stream context, inference mode, ``replay``), timed step by step in a
  tight loop (hot) and after what precedes it in a frame: the thread idle for 3 ms, a 6 MB frame copied by numpy, or
  both. Also the same launch with the stream set once per thread (``torch.cuda.set_stream``), with only the
  stream switched around it (a new or a reused stream context, or ``set_stream`` there and back), and as a raw
  ``cudaGraphLaunch`` (cuda-bindings) on the graph's exec handle.
* wake: one Python thread wakes another through a futex (as a head wakes ``Engine.wait``) and then keeps the
  interpreter lock busy for 0, 30 or 100 us (as a worker does, finishing its loop): how long until the woken thread
  runs. And the same when a third thread polls with ``time.sleep(0)`` (a spin-waiting worker).

Writes wakeups.json to $OUT.
"""

from __future__ import annotations

import ctypes
import json
import os
import threading
import time

import numpy as np
import torch

from vpengine.transport import _linux

out_dir = os.environ.get("OUT", "/tmp/out")
os.makedirs(out_dir, exist_ok=True)
report: dict[str, object] = {}


def us(a: list[float]) -> dict[str, float]:
    x = np.array(a[10:]) * 1e6
    return {"p50": round(float(np.median(x)), 1), "mean": round(float(x.mean()), 1)}


# ------------------------------------------------------------------------------------------------ cold launch
dev = torch.device("cuda")
stream = torch.cuda.Stream(dev)
x = torch.randn(1 << 20, device=dev)
y = torch.empty_like(x)
g = torch.cuda.CUDAGraph()
with torch.cuda.stream(stream):
    y.copy_(x * 2)  # warm-up
    torch.cuda.synchronize()
with torch.cuda.graph(g, stream=stream):
    y.copy_(x * 2)
torch.cuda.synchronize()
src = np.random.randint(0, 255, (1080, 1920, 3), np.uint8)
dst = np.empty_like(src)
raw = None
try:
    from cuda.bindings import runtime as cudart

    exec_handle = g.raw_cuda_graph_exec()
    raw = (cudart, exec_handle)
except Exception as e:  # a diagnostic: say why and go on
    report["raw_launch_unavailable"] = repr(e)


def before(kind: str) -> None:
    if kind in ("idle", "idle+copy"):
        time.sleep(0.003)
    if kind in ("copy", "idle+copy"):
        np.copyto(dst, src)


def launch_steps(kind: str, n: int = 300) -> dict[str, dict[str, float]]:
    steps: dict[str, list[float]] = {"stream context": [], "inference mode": [], "replay": [], "total": []}
    for _ in range(n):
        before(kind)
        t0 = time.perf_counter()
        with torch.cuda.stream(stream):
            t1 = time.perf_counter()
            with torch.inference_mode():
                t2 = time.perf_counter()
                g.replay()
                t3 = time.perf_counter()
        steps["stream context"].append(t1 - t0)
        steps["inference mode"].append(t2 - t1)
        steps["replay"].append(t3 - t2)
        steps["total"].append(t3 - t0)
        stream.synchronize()
    return {k: us(v) for k, v in steps.items()}


def launch_switched(kind: str, how: str, n: int = 300) -> dict[str, float]:
    """One replay on the stream from a thread whose current stream is another: a stream context made per launch
    (no inference mode), one StreamContext object reused, or set_stream there and back."""
    took = []
    reused = torch.cuda.StreamContext(stream)
    for _ in range(n):
        before(kind)
        t0 = time.perf_counter()
        if how == "new context":
            with torch.cuda.stream(stream):
                g.replay()
        elif how == "reused context":
            with reused:
                g.replay()
        else:
            prev = torch.cuda.current_stream(dev)
            torch.cuda.set_stream(stream)
            g.replay()
            torch.cuda.set_stream(prev)
        took.append(time.perf_counter() - t0)
        stream.synchronize()
    return us(took)


def launch_preset(kind: str, n: int = 300) -> dict[str, float]:
    """The stream set once for the thread, inference mode on for the thread: only the replay per frame."""
    took = []
    torch.cuda.set_stream(stream)
    with torch.inference_mode():
        for _ in range(n):
            before(kind)
            t0 = time.perf_counter()
            g.replay()
            took.append(time.perf_counter() - t0)
            stream.synchronize()
    torch.cuda.set_stream(torch.cuda.default_stream(dev))
    return us(took)


def launch_raw(kind: str, n: int = 300) -> dict[str, float]:
    assert raw is not None
    cudart, h = raw
    took = []
    for _ in range(n):
        before(kind)
        t0 = time.perf_counter()
        (err,) = cudart.cudaGraphLaunch(h, stream.cuda_stream)
        took.append(time.perf_counter() - t0)
        assert int(err) == 0, err
        stream.synchronize()
    return us(took)


cold: dict[str, object] = {}
for kind in ("hot", "idle", "copy", "idle+copy"):
    cold[kind] = {"steps": launch_steps(kind), "preset replay": launch_preset(kind)}
    for how in ("new context", "reused context", "set_stream and back"):
        cold[kind][f"replay, {how}"] = launch_switched(kind, how)  # type: ignore[index]
    if raw is not None:
        cold[kind]["raw cudaGraphLaunch"] = launch_raw(kind)  # type: ignore[index]
    print("launch", kind, json.dumps(cold[kind]))
report["launch_us"] = cold

# ------------------------------------------------------------------------------------------------ wake-ups
word = (ctypes.c_uint32 * 2)()
addr, back_addr = ctypes.addressof(word), ctypes.addressof(word) + 4


def busy(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def wake_latency(after_s: float, poller: bool, n: int = 300) -> dict[str, float]:
    lat: list[float] = []
    t_wake = [0.0]
    stop = threading.Event()

    def woken() -> None:
        for _ in range(n):
            w = word[0]
            while word[0] == w:
                _linux.futex_wait(addr, w, 0.5)
            lat.append(time.perf_counter() - t_wake[0])
            word[1] += 1
            _linux.futex_wake(back_addr)

    def poll() -> None:
        while not stop.is_set():
            time.sleep(0)

    th = threading.Thread(target=woken)
    th.start()
    pt = threading.Thread(target=poll) if poller else None
    for i in range(n):
        time.sleep(0.002)
        if pt is not None and i == 0:
            pt.start()
        w = word[1]
        t_wake[0] = time.perf_counter()
        word[0] += 1
        _linux.futex_wake(addr)
        busy(after_s)
        while word[1] == w:
            _linux.futex_wait(back_addr, w, 0.5)
    th.join()
    stop.set()
    if pt is not None:
        pt.join()
    return us(lat)


wake: dict[str, object] = {}
for poller in (False, True):
    for after in (0, 30e-6, 100e-6):
        key = f"waker busy {after * 1e6:.0f} us{', a thread polling with sleep(0)' if poller else ''}"
        wake[key] = wake_latency(after, poller)
        print("wake", key, wake[key])
report["wake_us"] = wake
with open(os.path.join(out_dir, "wakeups.json"), "w") as f:
    json.dump(report, f, indent=1)
