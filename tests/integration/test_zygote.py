"""Process-mode workers are forked from one pre-imported zygote (Note [Child lifecycle] in runtime/process.py):
they share it as parent, restart from it, die with it and come back from a new one, and nothing outlives the
engine."""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import psutil
import pytest

from helpers import waiting
from helpers.frames import frame
from helpers.waiting import alive
from tests_paths import ROOT, tiny
from vpengine.engine import Engine

pytestmark = pytest.mark.timeout(180)
HEADS = ("depth", "seg", "det")


wait_for = functools.partial(waiting.wait_for, timeout=30.0)


def zygotes(parent: psutil.Process | None = None) -> list[psutil.Process]:
    """The zygotes among ``parent``'s (this process's) children: a zygote's command line boots runtime.zygote."""
    out = []
    for p in (parent or psutil.Process()).children():
        with contextlib.suppress(psutil.NoSuchProcess):
            if any("vpengine.runtime.zygote" in a for a in p.cmdline()):
                out.append(p)
    return out


def worker_pids(e: Engine) -> dict[str, int]:
    return {n: m["pid"] for n, m in e.stats()["models"].items()}


def all_running(e: Engine, restarts: int) -> bool:
    return all(m["state"] == "running" and m["restarts"] == restarts for m in e.stats()["models"].values())


def serves_every_head(e: Engine, i: int) -> None:
    fid = e.submit(frame(i))
    got = e.wait(fid, timeout=20)
    assert set(got) == set(HEADS) and all(r.frame_id == fid for r in got.values())


@pytest.mark.parametrize(
    "fault,expected",
    [("sigsegv", "killed by signal 11"), ("raise", "exit code 1: RuntimeError: CUDA error: injected failure at run 2")],
)
def test_a_crashed_worker_restarts_from_the_zygote_and_its_exit_reaches_stats_and_log(
    tmp_path, caplog, restart_backoff, fault, expected
):
    opts = json.dumps(
        {"raise_at_run": 2 if fault == "raise" else None, "cuda_error": True, "once_marker": str(tmp_path / "once")}
    )
    cfg = tiny("process", "heads.seg.model=helpers.faulty:FaultyHead", f"heads.seg.options={opts}")
    restart_backoff(0.1)
    caplog.set_level(logging.WARNING, logger="vpengine")
    with Engine(cfg) as e:
        (zygote,) = zygotes()
        before = worker_pids(e)
        if fault == "sigsegv":
            os.kill(before["seg"], signal.SIGSEGV)
        else:
            for i in range(2):
                e.wait(e.submit(frame(i)), heads=["depth"], timeout=20)
        wait_for(
            lambda: e.stats()["models"]["seg"]["restarts"] == 1 and e.stats()["models"]["seg"]["state"] == "running",
            what="seg restarted",
            show=lambda: e.stats()["models"]["seg"],
        )
        seg = e.stats()["models"]["seg"]
        assert seg["crashes"] == 1 and seg["pid"] != before["seg"]
        assert psutil.Process(seg["pid"]).ppid() == zygote.pid  # the same zygote forked the new one
        assert zygotes() == [zygote]
        assert {n: p for n, p in worker_pids(e).items() if n != "seg"} == {
            n: p for n, p in before.items() if n != "seg"
        }
        assert any(f"seg stopped ({expected}" in r.getMessage() for r in caplog.records), caplog.text
        serves_every_head(e, 10)


def test_the_workers_are_forks_of_one_zygote_and_when_it_is_sigkilled_they_die_and_come_back_from_a_new_one(
    restart_backoff, caplog
):
    # one engine for both (a process-mode start takes seconds): the workers as the start made them, then the kill
    restart_backoff(0.1)
    caplog.set_level(logging.WARNING, logger="vpengine")
    with Engine(tiny("process")) as e:
        (old,) = zygotes()
        before = worker_pids(e)
        assert len(before) == 4
        for pid in before.values():
            worker = psutil.Process(pid)
            assert worker.ppid() == old.pid
            # forked, never exec'd: a worker started as its own interpreter would show its own command line
            assert worker.cmdline() == old.cmdline()
            assert worker.pid != worker.ppid() and os.getsid(pid) == pid  # a session of its own, as before
        maps = Path(f"/proc/{old.pid}/maps").read_text()
        assert "libtorch" in maps  # preloaded: the forks found it imported
        serves_every_head(e, 0)

        old.kill()
        wait_for(lambda: not alive(before.values()), timeout=10, what="the old workers gone")
        wait_for(lambda: all_running(e, 1), timeout=90, what="every worker restarted", show=lambda: e.stats())
        (new,) = zygotes()
        assert new.pid != old.pid and not alive([old.pid])
        after = worker_pids(e)
        assert not set(after.values()) & set(before.values())
        assert all(psutil.Process(p).ppid() == new.pid for p in after.values())
        assert all(m["crashes"] == 1 for m in e.stats()["models"].values())
        assert "killed by signal 9" in caplog.text
        serves_every_head(e, 0)
    assert not alive([new.pid, *after.values()])
    assert not [t.name for t in threading.enumerate() if t.name == "vpengine-zygote"]


ENGINE = """
    import json, os, time
    import psutil
    from tests_paths import tiny
    from vpengine.engine import Engine
    e = Engine(tiny("process")).start()
    kids = [p.pid for p in psutil.Process().children()]
    print(json.dumps({"zygotes": kids, "workers": [m["pid"] for m in e.stats()["models"].values()]}), flush=True)
    time.sleep(600)
"""


def test_sigkill_of_the_engine_leaves_no_zygote_and_no_worker(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT / "tests")])}
    script = tmp_path / "engine.py"
    script.write_text(textwrap.dedent(ENGINE))  # no __main__ guard needed: workers never re-import the user's script
    proc = subprocess.Popen([sys.executable, str(script)], cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True)
    pids: list[int] = []
    try:
        got = json.loads(proc.stdout.readline())
        pids = [*got["zygotes"], *got["workers"]]
        assert len(got["zygotes"]) == 1 and len(got["workers"]) == 4 and len(alive(pids)) == 5
        proc.kill()
        proc.wait(10)
        wait_for(lambda: not alive(pids), timeout=5, what="zygote and workers gone", show=lambda: alive(pids))
    finally:
        for p in alive(pids):
            with contextlib.suppress(ProcessLookupError):
                os.kill(p, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()


def test_stop_leaves_no_process_even_with_workers_stopped_by_sigstop():
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    e = Engine(tiny("process", "runtime.stop_timeout_s=0.5")).start()
    (zygote,) = zygotes()
    pids = list(worker_pids(e).values())
    os.kill(pids[1], signal.SIGSTOP)
    e.stop()
    assert not alive([zygote.pid, *pids])
    assert not alive({p.pid for p in psutil.Process().children(recursive=True)} - before)


def test_a_worker_that_dies_while_the_zygote_is_stopped_is_restarted_from_a_new_zygote(restart_backoff, caplog):
    # the stopped zygote reports nothing: the worker's pidfd tells its death, and the zygote counts as lost
    restart_backoff(0.1)
    caplog.set_level(logging.WARNING, logger="vpengine")
    e = Engine(tiny("process")).start()
    try:
        (old,) = zygotes()
        before = worker_pids(e)
        old.suspend()
        os.kill(before["seg"], signal.SIGKILL)
        wait_for(lambda: all_running(e, 1), timeout=90, what="every worker restarted", show=lambda: e.stats())
        (new,) = zygotes()
        assert new.pid != old.pid and not alive([old.pid, *before.values()])
        assert "did not report a worker's exit" in caplog.text
        assert "seg stopped (exit code unknown" in caplog.text
        after = worker_pids(e)
        serves_every_head(e, 0)
    finally:
        e.stop()
    assert not alive([new.pid, *after.values()])


FORKING_ENGINE = """
    import json, os, sys
    from helpers.frames import frame
    from tests_paths import tiny
    from vpengine.engine import Engine
    e = Engine(tiny("process")).start()
    before = {n: m["pid"] for n, m in e.stats()["models"].items()}
    child = os.fork()
    if child == 0:
        sys.exit(0)  # a helper of the user's program that ends normally: at exit, its copy of the engine is finalised
    _, status = os.waitpid(child, 0)
    fid = e.submit(frame(0))
    got = e.wait(fid, timeout=20)
    stats = e.stats()["models"]
    print(json.dumps({
        "child_status": status,
        "served": sorted(h for h, r in got.items() if r.frame_id == fid),
        "same_workers": {n: m["pid"] for n, m in stats.items()} == before,
        "restarts": sum(m["restarts"] for m in stats.values()),
    }), flush=True)
    e.stop()
"""


def test_a_process_forked_from_the_engine_that_exits_leaves_the_workers_serving():
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT / "tests")])}
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(FORKING_ENGINE)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=150,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got == {"child_status": 0, "served": sorted(HEADS), "same_workers": True, "restarts": 0}, out.stderr


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs to narrow the affinity")
def test_a_restarted_worker_takes_the_engines_affinity_and_load_time_variables(restart_backoff, monkeypatch):
    restart_backoff(0.1)
    e = Engine(tiny("process")).start()
    cpus = os.sched_getaffinity(0)
    try:
        (old,) = zygotes()
        before = worker_pids(e)
        os.sched_setaffinity(0, {min(cpus)})  # this thread is the engine's main thread
        monkeypatch.setenv("OMP_NUM_THREADS", "1" if os.environ.get("OMP_NUM_THREADS") != "1" else "2")
        os.kill(before["seg"], signal.SIGKILL)
        wait_for(lambda: e.stats()["models"]["seg"]["restarts"] == 1, what="seg restarted", show=e.stats)
        wait_for(lambda: e.stats()["models"]["seg"]["state"] == "running", what="seg running", show=e.stats)
        seg = psutil.Process(e.stats()["models"]["seg"]["pid"])
        assert seg.cpu_affinity() == [min(cpus)]
        new = [z for z in zygotes() if z.pid != old.pid]
        assert len(new) == 1 and seg.ppid() == new[0].pid  # OpenMP read OMP_NUM_THREADS as the old zygote loaded
        assert new[0].environ()["OMP_NUM_THREADS"] == os.environ["OMP_NUM_THREADS"]
        assert all(psutil.Process(p).ppid() == old.pid for n, p in worker_pids(e).items() if n != "seg")
        serves_every_head(e, 0)
        zs = [old.pid, new[0].pid]
    finally:
        os.sched_setaffinity(0, cpus)
        e.stop()
    assert not alive([*zs, seg.pid, *before.values()])


def _fork_a_worker(z):
    from vpengine.runtime.zygote import worker_path

    ours, theirs = socket.socketpair()
    try:
        return z.fork(dict(os.environ), worker_path(), os.getcwd(), sorted(os.sched_getaffinity(0)), theirs.fileno())
    finally:
        theirs.close()
        ours.close()  # the worker reads EOF and leaves (exit code 2)


def test_a_worker_has_the_pidfd_its_zygote_opened_and_a_second_close_releases_nothing():
    from vpengine.runtime import sockets
    from vpengine.runtime.zygote_handle import Zygote

    z = Zygote(lambda f: f(), 120, lambda: None, lambda: False)
    try:
        proc = _fork_a_worker(z)
        assert f"Pid:\t{proc.pid}\n" in Path(f"/proc/self/fdinfo/{proc.pidfd}").read_text()
        assert proc.wait(30) == 2
    finally:
        z.close(1.0)
    fd = z._fd
    sockets.hold_parent_end(fd)  # the number now belongs to another engine's socket
    try:
        z.close(1.0)  # a failed start stops twice
        assert fd in sockets._PARENT_ENDS
    finally:
        sockets.release_parent_end(fd)


def test_without_pidfd_a_worker_is_signalled_through_its_zygote(monkeypatch):
    from vpengine.runtime import zygote, zygote_handle

    # a zygote whose kernel has no pidfd (< 5.3)
    monkeypatch.setattr(zygote, "_BOOT", "import os; del os.pidfd_open; " + zygote._BOOT)
    z = zygote_handle.Zygote(lambda f: f(), 120, lambda: None, lambda: False)
    try:
        ours, theirs = socket.socketpair()
        try:
            proc = z.fork(
                dict(os.environ), zygote.worker_path(), os.getcwd(), sorted(os.sched_getaffinity(0)), theirs.fileno()
            )
        finally:
            theirs.close()
        assert proc.pidfd is None
        proc.kill()
        assert proc.wait(30) == -signal.SIGKILL
        proc.kill()  # reaped: nothing is sent, and nothing else is signalled
        ours.close()
    finally:
        z.close(1.0)


def test_system_exit_in_a_worker_exits_as_the_interpreter_would(capsys):
    from vpengine.runtime.zygote import exit_status

    assert exit_status(None) == 0 and exit_status(3) == 3
    assert exit_status("bye") == 1
    assert "bye" in capsys.readouterr().err
