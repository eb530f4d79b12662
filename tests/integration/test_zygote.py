"""Process-mode workers are forked from one pre-imported zygote (Note [Child lifecycle] in runtime/process.py):
they share it as parent, restart from it, die with it and come back from a new one, and nothing outlives the
engine."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import psutil
import pytest

from helpers.frames import frame
from tests_paths import ROOT, tiny
from vpengine.engine import Engine

pytestmark = pytest.mark.timeout(180)
HEADS = ("depth", "seg", "det")


def wait_for(cond, timeout=30.0, what="condition", show=None):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}" + (f": {show()}" if show else ""))


def alive(pids) -> list[int]:
    out = []
    for p in pids:
        try:
            if psutil.Process(p).status() != psutil.STATUS_ZOMBIE:
                out.append(p)
        except psutil.NoSuchProcess:
            pass
    return out


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


def test_the_workers_of_an_engine_are_forks_of_one_zygote_that_imported_torch():
    with Engine(tiny("process")) as e:
        (zygote,) = zygotes()
        pids = worker_pids(e)
        assert len(pids) == 4
        for pid in pids.values():
            worker = psutil.Process(pid)
            assert worker.ppid() == zygote.pid
            # forked, never exec'd: a worker started as its own interpreter would show its own command line
            assert worker.cmdline() == zygote.cmdline()
            assert worker.pid != worker.ppid() and os.getsid(pid) == pid  # a session of its own, as before
        maps = Path(f"/proc/{zygote.pid}/maps").read_text()
        assert "libtorch" in maps  # preloaded: the forks found it imported
        serves_every_head(e, 0)
    assert not alive([zygote.pid, *pids.values()])
    assert not [t.name for t in threading.enumerate() if t.name == "vpengine-zygote"]


@pytest.mark.parametrize(
    "fault,expected",
    [("sigsegv", "killed by signal 11"), ("raise", "exit code 1: RuntimeError: injected failure at run 2")],
)
def test_a_crashed_worker_restarts_from_the_zygote_and_its_exit_reaches_stats_and_log(
    tmp_path, caplog, restart_backoff, fault, expected
):
    opts = json.dumps({"raise_at_run": 2 if fault == "raise" else None, "once_marker": str(tmp_path / "once")})
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


def test_sigkill_of_the_zygote_kills_its_workers_and_they_come_back_from_a_new_one(restart_backoff, caplog):
    restart_backoff(0.1)
    caplog.set_level(logging.WARNING, logger="vpengine")
    with Engine(tiny("process")) as e:
        (old,) = zygotes()
        before = worker_pids(e)
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


def test_sigkill_of_the_engine_leaves_no_zygote_and_no_worker():
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT / "tests")])}
    proc = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(ENGINE)], cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True
    )
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
