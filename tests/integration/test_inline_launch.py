"""Note [Inline launch]: in thread mode, the thread that publishes a frame queues the foundation model's work itself
when the foundation worker is armed for one. On the CPU (turned on for every worker by ``helpers.inline``; an engine
uses it only for CUDA graphs) the submitting thread then runs the model, which these tests can see; the CUDA path is
in tests/gpu/test_inline_launch_cuda.py."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from helpers.frames import frame
from helpers.inline import inline_launch
from helpers.models import ThreadNotingViT
from tests_paths import tiny
from vpengine.engine import Engine

pytestmark = pytest.mark.timeout(120)
NOTING = "foundation_model.model=helpers.models:ThreadNotingViT"


@contextlib.contextmanager
def engine(inline: bool, *overrides: str) -> Iterator[Engine]:
    with inline_launch(inline), Engine(tiny("thread", NOTING, *overrides)) as e:
        yield e


def lockstep(e: Engine, n: int, armed: bool = False) -> dict[int, dict[str, dict[str, np.ndarray]]]:
    """Submit ``n`` frames one at a time, each after the last one's results; with ``armed``, each once the
    foundation worker is armed for it (a busy machine can keep its thread from re-arming for a while)."""
    out = {}
    offer = e._handoffs.inline
    for i in range(n):
        if armed:
            deadline = time.monotonic() + 5.0
            while offer._launch is None and time.monotonic() < deadline:
                time.sleep(0.001)
        res = e.wait(e.submit(frame(i), frame_id=i), timeout=10)
        assert set(res) == {"depth", "seg", "det"} and all(r.frame_id == i for r in res.values())
        out[i] = {h: {k: np.array(v) for k, v in r.outputs.items()} for h, r in res.items()}
    return out


def test_the_submitting_thread_runs_the_armed_foundation_and_every_output_is_the_same():
    me = threading.current_thread().name
    inference = []  # whether each run had inference mode on
    with engine(False) as e:
        ThreadNotingViT.threads.clear()
        ThreadNotingViT.inference.clear()
        plain = lockstep(e, 12)
        assert ThreadNotingViT.threads == ["vpengine-foundation"] * 12
        inference += ThreadNotingViT.inference
    with engine(True) as e:
        ThreadNotingViT.threads.clear()
        ThreadNotingViT.inference.clear()
        inline = lockstep(e, 12, armed=True)
        st = e.stats()["models"]["foundation"]
        launches = e.stats()["engine"]["launched_by_submit"]
        inference += ThreadNotingViT.inference
    # the worker's loop runs in inference mode (entered once, Note [Launch path]), and so does a launch from submit
    assert inference == [True] * 24
    # submitted to an armed worker, a frame is launched by the submitting thread; one that lands in the moment the
    # worker re-arms after its poll times out is run by the worker: still once
    assert len(ThreadNotingViT.threads) == 12 and st["runs"] == 12 and st["errors"] == 0
    assert ThreadNotingViT.threads.count(me) == launches >= 11
    for i in plain:
        for h in plain[i]:
            for k, v in plain[i][h].items():
                assert np.array_equal(inline[i][h][k], v), (i, h, k)


def test_frames_submitted_faster_than_the_foundation_runs_are_all_run_or_counted_skipped():
    opts = '{"sleep_ms": 5}'  # a head slower than the frames come: the foundation's slots turn over
    with engine(True, "heads.depth.model=helpers.faulty:FaultyHead", f"heads.depth.options={opts}") as e:
        last = 0
        for i in range(150):
            last = e.submit(frame(i % 8))
        assert "depth" in e.wait(last, timeout=10)  # the newest frame is always run
        fm = e.stats()["models"]["foundation"]
        assert fm["runs"] + fm["skipped"] == 150 and fm["errors"] == 0, fm
        assert e.stats()["engine"]["launched_by_submit"] > 0


def test_a_paused_foundation_takes_no_frame_from_submit_and_resumes():
    with engine(True) as e:
        for _ in range(8):  # the pause lands wherever the worker is: armed, at its gate, or between the two
            lockstep(e, 2)
            e.set_rate("foundation", 0)
            runs = e.stats()["models"]["foundation"]["runs"]
            for i in range(5):
                e.submit(frame(i))  # at once: the worker may still be armed from before the pause
                time.sleep(0.01)
            time.sleep(0.1)
            assert e.stats()["models"]["foundation"]["runs"] == runs
            e.set_rate("foundation", None)
            fid = e.submit(frame(7))
            assert set(e.wait(fid, timeout=10)) == {"depth", "seg", "det"}


def test_stop_wakes_an_armed_foundation_at_once(monkeypatch):
    from vpengine.runtime.worker import WorkerCore

    init = WorkerCore.__init__

    def long_poll(self, *args, **kwargs):  # a long poll, so that waiting one out cannot pass for a wake-up
        init(self, *args, **kwargs)
        self.poll_s = 10.0

    monkeypatch.setattr(WorkerCore, "__init__", long_poll)
    with engine(True) as e:
        lockstep(e, 2)
        time.sleep(0.1)  # armed, waiting for a frame
        t0 = time.monotonic()
        e.stop()
        assert time.monotonic() - t0 < 5.0  # woken, not the 10 s poll waited out


def test_rate_changes_while_frames_stream_in_leave_every_frame_run_or_counted():
    """Pauses, limits and unlimited, changed every few ms from another thread while frames come as fast as submit
    takes them: no error, no hang, and every frame is run or counted skipped."""
    imgs = [frame(i) for i in range(4)]
    with engine(True) as e:
        done = threading.Event()

        def change_rates() -> None:
            rates = [None, 0.0, 20.0, 200.0]
            i = 0
            while not done.is_set():
                e.set_rate("foundation", rates[i % len(rates)])
                i += 1
                time.sleep(0.004 * (1 + i % 5))

        t = threading.Thread(target=change_rates)
        t.start()
        # 3 s of frames, longer (up to 30 s) until one was launched by submit: a loaded machine can keep the
        # worker from re-arming for a while, and a run without an inline launch tests nothing of it
        n, t0, launched, look = 0, time.monotonic(), 0, 0.0
        try:
            while (elapsed := time.monotonic() - t0) < 3.0 or (not launched and elapsed < 30.0):
                e.submit(imgs[n % 4])
                n += 1
                if elapsed >= look:
                    launched, look = e.stats()["engine"]["launched_by_submit"], elapsed + 0.25
        finally:
            done.set()
            t.join()
        e.set_rate("foundation", None)
        last = e.submit(imgs[0])
        assert set(e.wait(last, timeout=10)) == {"depth", "seg", "det"}
        fm = e.stats()["models"]["foundation"]
        assert fm["errors"] == 0 and fm["runs"] + fm["skipped"] == n + 1, (n, fm)
        assert e.stats()["engine"]["launched_by_submit"] > 0
