"""Note [Process groups] in runtime/process.py: models naming one ``process`` share a worker process in process mode,
each on its own thread; the process is the unit of restart; a head that shares one is neither added to it nor
removed from it while the engine runs."""

from __future__ import annotations

import json
import os
import signal

import pytest

from helpers.frames import frame
from helpers.waiting import wait_for
from tests_paths import tiny
from vpengine.engine import Engine
from vpengine.engine.stats import processes

pytestmark = pytest.mark.timeout(120)


def pids(e: Engine) -> dict[str, int]:
    return {m: s["pid"] for m, s in e.stats()["models"].items()}


def every_head(e: Engine, n: int, start: int = 0) -> None:
    for i in range(n):
        assert set(e.wait(e.submit(frame(start + i)), timeout=20)) == {"depth", "seg", "det"}


@pytest.mark.parametrize("together", [("depth", "seg"), ("foundation", "depth", "seg", "det")])
def test_models_naming_one_process_share_it_and_serve_every_frame(together):
    sets = [f"{'foundation_model' if m == 'foundation' else 'heads.' + m}.process=shared" for m in together]
    with Engine(tiny("process", *sets)) as e:
        every_head(e, 6)
        p = pids(e)
        assert len({p[m] for m in together}) == 1  # one process
        assert len(set(p.values())) == 4 - len(together) + 1  # the others alone
        assert os.getpid() not in p.values()
        names = processes(p)  # how reports name processes: a shared one once, under all its models
        assert "+".join(together) in names.values() and names[os.getpid()] == "engine (parent)"
        assert len(names) == len(set(p.values())) + 1


def test_a_crash_restarts_every_model_of_the_process_once_and_it_is_neither_joined_nor_left_at_run_time(
    restart_backoff,
):
    # one engine for both (a process-mode start takes seconds): the crash first, then the changes refused and
    # allowed, on the engine as the restart left it
    restart_backoff(0.2)
    with Engine(tiny("process", "heads.depth.process=heads", "heads.seg.process=heads")) as e:
        every_head(e, 3)
        before = pids(e)
        os.kill(before["depth"], signal.SIGKILL)
        wait_for(
            lambda: all(
                e.stats()["models"][m]["state"] == "running" and pids(e)[m] != before[m] for m in ("depth", "seg")
            ),
            what="the process restarted",
            show=lambda: e.stats()["models"],
        )
        after, models = pids(e), e.stats()["models"]
        assert after["depth"] == after["seg"] and after["det"] == before["det"]
        assert [models[m]["crashes"] for m in ("depth", "seg", "det")] == [1, 1, 0]
        assert [models[m]["restarts"] for m in ("depth", "seg", "det")] == [1, 1, 0]
        every_head(e, 3, start=3)

        with pytest.raises(ValueError, match=r"process 'heads' is the running process of \['depth', 'seg'\]"):
            e.add_head({"name": "det2", "model": "tiny_det", "process": "heads"})
        with pytest.raises(ValueError, match=r"'seg' shares process 'heads' with \['depth'\]"):
            e.remove_head("seg")
        e.add_head({"name": "det2", "model": "tiny_det", "process": "spare"})  # a new name: a process of its own
        assert len(set(pids(e).values())) == 4
        e.remove_head("det2")
        e.remove_head("det")
        assert set(e.wait(e.submit(frame(0)), timeout=20)) == {"depth", "seg"}


def test_a_model_that_hangs_takes_its_process_down_and_both_come_back(restart_backoff):
    restart_backoff(0.2)
    opts = json.dumps({"hang_at_run": 3, "once_marker": None})
    cfg = tiny(
        "process",
        "heads.seg.model=helpers.faulty:FaultyHead",
        f"heads.seg.options={opts}",
        "heads.seg.process=heads",
        "heads.depth.process=heads",
        "runtime.hang_timeout_s=1.5",
    )
    with Engine(cfg) as e:
        before = pids(e)
        sent = iter(range(10**6))

        def restarted() -> bool:  # frames until seg has run its third (a loaded machine may skip some)
            e.wait(e.submit(frame(next(sent))), heads=["det"], timeout=20)
            return e.stats()["models"]["depth"]["restarts"] >= 1

        wait_for(restarted, timeout=40, what="the group restarted")
        models = e.stats()["models"]
        assert models["seg"]["crashes"] >= 1 and models["depth"]["crashes"] >= 1 and models["det"]["crashes"] == 0
        for name in ("seg", "depth"):  # each says why its process stopped, depth for seg's hang
            assert "hung for" in models[name]["last_error"] and "process stopped" in models[name]["last_error"]
        assert pids(e)["det"] == before["det"]
        wait_for(lambda: pids(e)["depth"] == pids(e)["seg"] != before["depth"], what="one new process for both")


def test_a_failed_restart_of_a_process_fails_every_model_in_it(restart_backoff):
    """One process, one decision: when the process has crashed past runtime.max_restarts, every model in it is
    failed, none comes back in another's restart."""
    restart_backoff(0.1)
    cfg = tiny("process", "heads.depth.process=heads", "heads.seg.process=heads", "runtime.max_restarts=1")
    with Engine(cfg) as e:
        for n in (1, 2):
            pid = pids(e)["depth"]
            os.kill(pid, signal.SIGKILL)
            wait_for(
                lambda pid=pid: pids(e)["depth"] != pid or e.stats()["models"]["depth"]["state"] == "failed",
                what=f"crash {n} handled",
            )
        wait_for(lambda: e.stats()["models"]["seg"]["state"] == "failed", what="both failed")
        models = e.stats()["models"]
        assert [models[m]["state"] for m in ("depth", "seg", "det")] == ["failed", "failed", "running"]
        assert [models[m]["restarts"] for m in ("depth", "seg")] == [1, 1]
        assert set(e.wait(e.submit(frame(0)), timeout=20)) == {"det"}


def test_a_restart_that_cannot_launch_the_process_fails_every_model_in_it(restart_backoff, monkeypatch):
    """A relaunch that fails is a crash of every model of the process: they restart again or fail together, and
    ``wait`` stops waiting for the failed ones."""
    import vpengine.runtime.process

    restart_backoff(0.1)
    cfg = tiny("process", "heads.depth.process=heads", "heads.seg.process=heads", "runtime.max_restarts=1")
    with Engine(cfg) as e:

        def no_launch(*args, **kw):
            raise OSError("no more processes")

        monkeypatch.setattr(vpengine.runtime.process, "start_with_socket", no_launch)
        os.kill(pids(e)["depth"], signal.SIGKILL)
        wait_for(lambda: e.stats()["models"]["depth"]["state"] == "failed", what="the first failed")
        models = e.stats()["models"]
        assert [models[m]["state"] for m in ("depth", "seg", "det")] == ["failed", "failed", "running"]
        assert [(models[m]["restarts"], models[m]["crashes"]) for m in ("depth", "seg")] == [(1, 2), (1, 2)]
        assert set(e.wait(e.submit(frame(0)), timeout=20)) == {"det"}


def test_thread_mode_ignores_processes():
    with Engine(tiny("thread", "heads.depth.process=heads", "heads.seg.process=heads")) as e:
        every_head(e, 2)
        e.remove_head("seg")
