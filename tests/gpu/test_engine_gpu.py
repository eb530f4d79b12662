"""The engine on a CUDA GPU (run on the GPU machine: pytest -m gpu tests/gpu)."""

from __future__ import annotations

import gc
import json
import os
import signal
import socket
import subprocess
import sys
import time
from multiprocessing.connection import Connection

import numpy as np
import psutil
import pytest
import torch

from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.timeout(600),
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU"),
]

CHILD_WRITER = """
import sys, torch
from multiprocessing.connection import Connection
from vpengine.runtime.process import recv_fds
from vpengine.transport.memory import open_region
conn = Connection(int(sys.argv[1]))
handle = conn.recv()
region = open_region(handle, recv_fds(conn))
t = region.tensor()
t.view(torch.int32)[: t.numel() // 4].copy_(torch.arange(t.numel() // 4, dtype=torch.int32, device=t.device) * 7)
torch.cuda.synchronize()
conn.send(("written", int(region.ptr)))
conn.recv()
region.close()
"""


def _spawn(script: str):
    from vpengine.runtime.process import package_env

    ours, theirs = socket.socketpair()
    proc = subprocess.Popen(
        [sys.executable, "-c", script, str(theirs.fileno())], pass_fds=[theirs.fileno()], env=package_env()
    )
    theirs.close()
    return proc, Connection(ours.detach())


def test_vmm_region_is_shared_between_processes_without_copies():
    from vpengine.runtime.process import send_fds
    from vpengine.transport.cuda_vmm import CudaVmmRegion

    region = CudaVmmRegion("shared", 3 * 2**20 + 12, "cuda:0")
    region.tensor().fill_(0)
    proc, conn = _spawn(CHILD_WRITER)
    try:
        fds: list[int] = []
        conn.send(region.export(fds))
        send_fds(conn, fds)
        kind, _child_ptr = conn.recv()
        assert kind == "written"
        n = region.tensor().numel() // 4
        got = region.tensor().view(torch.int32)[:n]
        assert torch.equal(got, torch.arange(n, dtype=torch.int32, device="cuda") * 7)  # the child's writes, here
        conn.send("done")
        proc.wait(30)
        assert proc.returncode == 0
        # the child is gone; the memory is ours still
        assert torch.equal(
            region.tensor().view(torch.int32)[:n][-3:],
            torch.arange(n - 3, n, dtype=torch.int32, device="cuda") * 7,
        )
    finally:
        conn.close()
        region.close()


def _engine_pids(e: Engine) -> list[int]:
    return [m["pid"] for m in e.stats()["models"].values()]


@pytest.mark.parametrize("mode", ["process", "thread"])
def test_device_memory_is_flat_between_frame_1000_and_10000(mode):
    from vpengine.runtime.gpu import process_memory

    cfg = tiny(mode, "device=cuda", "input.height=540", "input.width=960")
    imgs = [frame(i, 540, 960) for i in range(8)]
    with Engine(cfg) as e:
        pids = set(_engine_pids(e)) | {os.getpid()}
        samples = {}
        for i in range(1, 10001):
            fid = e.submit(imgs[i % 8])
            e.wait(fid, timeout=10)  # lockstep: every model processes every one of the 10,000 frames
            if i in (1000, 10000):
                torch.cuda.synchronize()
                time.sleep(0.2)
                mem = process_memory(0)
                samples[i] = {p: mem.get(p) for p in pids}
        st = e.stats()
    assert all(v is not None for v in samples[1000].values()), f"NVML did not report every process: {samples}"
    assert samples[1000] == samples[10000], f"device memory changed: {samples}"
    assert all(m["runs"] >= 10000 for m in st["models"].values()), {k: m["runs"] for k, m in st["models"].items()}


def test_thread_mode_host_mailboxes_are_page_locked_so_gpu_copies_do_not_block_the_worker():
    # From pageable memory, copy_(non_blocking=True) quietly blocks the worker's thread for the whole copy.
    cfg = tiny("thread", "device=cuda", "input.height=540", "input.width=960")
    with Engine(cfg) as e:
        rings = e._res.rings
        host = {n: r for n, r in rings.items() if r.data_region.device.type == "cpu"}
        assert set(host) >= {"input", *(f"out.{h}" for h in e.plan.heads)}, sorted(host)
        assert all(r.data_region.tensor().is_pinned() for r in host.values()), {
            n: r.data_region.tensor().is_pinned() for n, r in host.items()
        }
        out = e.wait(e.submit(frame(0, 540, 960)), timeout=30)
        assert set(out) == set(e.plan.heads)


def test_stop_leaves_no_process_and_gives_the_device_memory_back():
    from vpengine.runtime.gpu import device_memory_used

    torch.cuda.init()
    torch.empty(1, device="cuda")  # this process's own context exists before we measure
    torch.cuda.synchronize()
    before = device_memory_used(0)
    e = Engine(tiny("process", "device=cuda")).start()
    pids = _engine_pids(e)
    during = device_memory_used(0)
    e.wait(e.submit(frame(0)), timeout=10)
    e.stop()
    time.sleep(1.0)
    after = device_memory_used(0)
    assert not [p for p in pids if psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE]
    assert during > before
    assert abs(after - before) <= 4 * 2**20, f"device memory before {before}, after {after} (during {during})"


def test_sigkilled_head_on_gpu_restarts_and_the_others_stay_correct():
    cfg = tiny("process", "device=cuda")  # the default first restart delay, 0.5 s
    with Engine(cfg) as e:
        ref = {}
        for i in range(5):
            fid = e.submit(frame(i))
            ref[i] = e.wait(fid, timeout=10)
        os.kill(e.stats()["models"]["seg"]["pid"], signal.SIGKILL)
        for i in range(5, 40):
            fid = e.submit(frame(i % 5))  # same content as before: outputs must equal the earlier ones
            got = e.wait(fid, heads=["depth", "det"], timeout=10)
            for h in ("depth", "det"):
                for k, v in got[h].outputs.items():
                    np.testing.assert_allclose(
                        np.asarray(v), np.asarray(ref[i % 5][h].outputs[k]), rtol=1e-4, atol=1e-5
                    )
            time.sleep(0.05)
        deadline = time.monotonic() + 60
        while e.stats()["models"]["seg"]["state"] != "running" and time.monotonic() < deadline:
            time.sleep(0.1)
        assert e.stats()["models"]["seg"]["restarts"] == 1
        fid = e.submit(frame(1))
        assert e.wait(fid, timeout=10)["seg"].frame_id == fid


def _mps_processes() -> list[psutil.Process]:
    out = []
    for p in psutil.process_iter(["name", "cmdline"]):
        name = (p.info["name"] or "") + " ".join(p.info["cmdline"] or [])
        if "nvidia-cuda-mps" in name:
            out.append(p)
    return out


def test_results_keep_coming_when_the_mps_daemon_is_killed(tmp_path, monkeypatch, restart_backoff):
    from vpengine.runtime import mps

    restart_backoff(0.2)

    if not __import__("shutil").which(mps.CONTROL):
        pytest.fail("nvidia-cuda-mps-control is not installed on this GPU machine")
    pipe = str(tmp_path / "mps")
    before = {p.pid for p in _mps_processes()}
    mps.start(pipe)
    monkeypatch.setenv("CUDA_MPS_PIPE_DIRECTORY", pipe)  # where the engine looks first
    try:
        # clients of a dead MPS server may hang inside CUDA rather than fail: the hang timeout catches those
        cfg = tiny(
            "process",
            "device=cuda",
            "mps=required",
            "runtime.hang_timeout_s=5",
        )
        with Engine(cfg) as e:
            for i in range(20):
                e.wait(e.submit(frame(i)), timeout=10)
            on_mps = {n: m["mps"] for n, m in e.stats()["models"].items()}
            assert all(on_mps.values()), f"workers not on MPS: {on_mps}"
            for p in _mps_processes():
                if p.pid not in before:
                    p.kill()
            got = 0
            deadline = time.monotonic() + 120
            i = 0
            while time.monotonic() < deadline and got < 30:
                fid = e.submit(frame(i % 8))
                i += 1
                try:
                    r = e.wait(fid, timeout=2)
                    got += len(r) == 3
                except TimeoutError:
                    pass
            st = e.stats()["models"]
            assert got >= 30, f"results stopped after the MPS daemon died: {st}"
            assert not any(m["mps"] for m in st.values()), "restarted workers should run without MPS"
            assert all(m["restarts"] >= 1 for m in st.values())
    finally:
        mps.stop(pipe)
        for p in _mps_processes():
            if p.pid not in before:
                p.kill()


def test_thread_mode_gives_each_model_the_device_memory_it_holds_alone():
    """stats()' device_mem_bytes in thread mode (docs/config.md, modes): a model's weights, and for a compiled one its
    static inputs and CUDA graphs' pool; together less than the process reserved, each a real share."""
    compiled = ["foundation_model.backend=compile", "heads.depth.backend=compile"]
    with Engine(tiny("thread", "device=cuda", *compiled)) as e:
        e.wait(e.submit(frame(0)), timeout=120)
        held = {n: m["device_mem_bytes"] for n, m in e.stats()["models"].items()}
        assert held == e.stats()["memory"]["models_device_bytes"]
        reserved = torch.cuda.memory_reserved()
        assert 0 < sum(held.values()) < reserved, (held, reserved)
        from vpengine.backends.compiled import CompiledExecutor

        weights = {}
        for o in gc.get_objects():
            if type(o) is CompiledExecutor and o.device.type == "cuda":
                weights[o.name] = sum(p.numel() * p.element_size() for p in o.model.parameters())
        assert set(weights) >= {"foundation", "depth"}
        for name in ("foundation", "depth"):  # a graph pool of its own on top of the weights
            assert held[name] > weights[name] + 2**20, (name, held[name], weights[name])
        assert held["seg"] > 0 and held["det"] > 0  # eager: weights only


def test_bench_cameras_in_thread_mode_runs_its_engines_one_after_another_in_one_process(tmp_path):
    """``vpengine bench cameras`` in thread mode, 4 cameras (compiled models at batches 1-4): its stream run's
    engine, then the throughput run's engines (one of 4 cameras, then four of one, started side by side), all in one
    process. Counting each model's graph pool for stats() once crashed that process at the second engine's start
    (torch 2.11's memory_snapshot of one pool: three runs of three; an engine after another with nothing else did
    not crash). In a child process, so a crash fails this test rather than ending the run."""
    from vpengine.runtime.process import package_env

    args = ["--set", "mode=thread", "--stream-cameras", "4", "--seconds", "3", "--cameras", "4"]
    args += ["--point-seconds", "2", "--rounds", "10", "--out", str(tmp_path), "--name", "cams"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "vpengine.cli.main", "bench", "cameras", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=package_env(),
        start_new_session=True,  # its compile workers too go with it on a timeout
    )
    try:
        _, err = proc.communicate(timeout=500)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, (proc.returncode, err[-3000:])
    result = json.loads((tmp_path / "cams.json").read_text())
    assert result["stream"] and result["throughput"], result
