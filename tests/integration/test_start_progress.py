"""Note [Start progress] in runtime/supervisor.py: a start waits while the models' builds make progress, gives up
after runtime.ready_timeout_s without any, and says meanwhile where each model is.

The slow build is the eager backend's set-up made slow for one head, in thread mode (the same process, so the test
can slow it): it reports its steps as the compile backend does for each batch size (``Executor.progress``)."""

from __future__ import annotations

import logging
import time

import pytest

from tests_paths import tiny
from vpengine.backends.eager import EagerExecutor
from vpengine.engine import Engine
from vpengine.models.build import build_lock
from vpengine.runtime import supervisor
from vpengine.runtime.supervisor import EngineStartError

STEPS = 10


def _slow_depth(monkeypatch: pytest.MonkeyPatch, step_s: float, report: bool) -> None:
    """depth's set-up takes STEPS x ``step_s``, reporting each step (``report``) or none."""
    setup = EagerExecutor._setup

    def slow(self: EagerExecutor, model) -> None:  # type: ignore[no-untyped-def]
        setup(self, model)
        if self.name != "depth":
            return
        for i in range(1, STEPS + 1):
            time.sleep(step_s)
            if report:
                self.progress(i, STEPS)

    monkeypatch.setattr(EagerExecutor, "_setup", slow)


def test_a_build_longer_than_the_ready_timeout_that_makes_progress_starts(monkeypatch, caplog):
    monkeypatch.setattr(supervisor, "PROGRESS_S", 0.3)
    _slow_depth(monkeypatch, 0.5, report=True)  # 5 s in all, 0.5 s a step, against a 2.5 s timeout
    t = time.monotonic()
    with (
        caplog.at_level(logging.INFO, logger="vpengine.start"),
        Engine(tiny("thread", "runtime.ready_timeout_s=2.5")) as eng,
    ):
        took = time.monotonic() - t
        assert took >= 0.5 * STEPS, took  # it did wait for the whole build, twice its timeout
        fid = eng.submit(eng_frame(eng))
        assert set(eng.wait(fid, timeout=30)) == {"depth", "seg", "det"}
    lines = [r.getMessage() for r in caplog.records if r.name == "vpengine.start"]
    assert lines, "a start of seconds said nothing about where it was"
    assert all(line.startswith("starting, ") for line in lines), lines
    steps = [line for line in lines if "depth " in line and f" of {STEPS} steps" in line]
    assert steps, lines  # where depth's build was, step by step
    assert "later starts read the compile cache" in steps[-1]


def test_a_build_without_progress_ends_the_start_after_the_ready_timeout(monkeypatch):
    _slow_depth(monkeypatch, 0.6, report=False)  # 6 s without a step
    t = time.monotonic()
    try:
        with pytest.raises(
            EngineStartError, match=r"were not ready: no progress for 1(\.0)? s \(runtime\.ready_timeout_s\)"
        ):
            Engine(tiny("thread", "runtime.ready_timeout_s=1", "runtime.stop_timeout_s=0.3")).start()
        took = time.monotonic() - t
        assert took < 5, took  # it gave up 1 s after the last step, not when the build ended
    finally:  # the build left behind holds the build lock until it returns (Note [One build at a time])
        deadline = time.monotonic() + 10
        while build_lock.holder() is not None and time.monotonic() < deadline:
            time.sleep(0.05)


def eng_frame(eng: Engine):  # type: ignore[no-untyped-def]
    import numpy as np

    cfg = eng.config.input
    return np.zeros((cfg.height, cfg.width, 3), dtype=np.uint8)


def test_a_process_mode_start_says_where_each_model_is(monkeypatch, caplog):
    """The same wait in process mode, where the workers report from their own processes."""
    monkeypatch.setattr(supervisor, "PROGRESS_S", 0.0)  # every turn of the wait says it
    with caplog.at_level(logging.INFO, logger="vpengine.start"), Engine(tiny("process")) as eng:
        fid = eng.submit(eng_frame(eng))
        assert set(eng.wait(fid, timeout=30)) == {"depth", "seg", "det"}
    lines = [r.getMessage() for r in caplog.records if r.name == "vpengine.start"]
    assert lines and all(line.startswith("starting, ") for line in lines), lines
    names = ("foundation", "depth", "seg", "det")
    assert all(f"{n} " in lines[-1] for n in names), lines[-1]  # every model, each with where it is
    assert any(" loading" in line or " starting" in line for line in lines), lines
