"""bench cameras' throughput points: every camera's pump counted, a point at least as long as asked, a failed pump
an error rather than a rate over frames that never ran, a file run's frames in flight and every one answered."""

from __future__ import annotations

import statistics
import time
import types

import pytest

from vpengine.bench.cameras import _all_cameras

HEADS = {"depth", "seg"}


class Engine:
    """submit/wait of an engine whose every frame takes ``step`` seconds; ``fail_at`` frames in, wait raises. A
    frame's results are there ``ready`` s after its submit, and wait returns ``read`` s after that (or after it is
    called, if later)."""

    def __init__(
        self, step: float, fail_at: int | None = None, torn_at: int | None = None, ready: float = 0.0, read: float = 0.0
    ) -> None:
        self.step, self.fail_at, self.torn_at, self.n = step, fail_at, torn_at, 0
        self.ready, self.read = ready, read
        self.open: list[int] = []  # submitted, not yet waited for
        self.submitted: dict[int, float] = {}
        self.most_open = 0

    def submit(self, img, camera=None):
        self.n += 1
        self.open.append(self.n)
        self.submitted[self.n] = time.monotonic()
        self.most_open = max(self.most_open, len(self.open))
        return self.n

    def wait(self, fid, timeout):
        assert fid == self.open.pop(0), "answers waited for out of order"
        if fid == self.fail_at:
            raise TimeoutError(f"frame {fid}: no result")
        time.sleep(self.step)
        there = self.submitted.pop(fid) + self.ready
        time.sleep(max(0.0, there - time.monotonic()) + self.read)
        heads = ["depth"] if fid == self.torn_at else ["depth", "seg"]  # torn: seg's was overwritten
        # the heads' results come one after the other, seg's last
        return {h: types.SimpleNamespace(t_publish=there - (0.005 if h == "depth" else 0.0)) for h in heads}


def test_a_point_runs_its_rounds_and_at_least_its_seconds():
    engines = [Engine(0.01), Engine(0.01)]
    t = time.monotonic()
    fps, _, torn, _ = _all_cameras(
        [(e, None) for e in engines], [None], rounds=3, seconds=0.3, in_flight=1, heads=HEADS
    )
    took = time.monotonic() - t
    assert took >= 0.3 and all(e.n > 3 for e in engines)
    assert fps == pytest.approx(sum(e.n for e in engines) / took, rel=0.05) and torn == 0
    quick = [Engine(0.0), Engine(0.0)]
    _all_cameras([(e, None) for e in quick], [None], rounds=5, seconds=0.0, in_flight=1, heads=HEADS)
    assert [e.n for e in quick] == [5, 5]


def test_a_pump_that_fails_fails_the_point():
    with pytest.raises(RuntimeError, match="1 of 2 cameras' pumps failed: TimeoutError: frame 2: no result"):
        _all_cameras(
            [(Engine(0.0), None), (Engine(0.0, fail_at=2), None)],
            [None],
            rounds=5,
            seconds=0.0,
            in_flight=1,
            heads=HEADS,
        )


def test_a_pump_keeps_its_frames_in_flight_waits_for_every_one_and_counts_only_whole_frames():
    engines = [Engine(0.0), Engine(0.0, torn_at=4)]
    _, whole, torn, spent = _all_cameras(
        [(e, None) for e in engines], [None], rounds=10, seconds=0.0, in_flight=3, heads=HEADS
    )
    assert [(e.n, e.most_open, e.open) for e in engines] == [(10, 3, []), (10, 3, [])]
    assert (whole, torn) == (19, 1)  # the frame without seg's output is not counted through every head
    assert len(spent["ready"]) == len(spent["read"]) == 19  # where the time went: whole frames only


@pytest.mark.parametrize(
    "in_flight, ready, read",
    [
        (1, 0.06, 0.04),  # each wait is called at once: before the results come (not counted as reading)
        (3, 0.005, 0.04),  # most are called well after their results came (the time before is not reading either)
    ],
)
def test_a_frames_time_is_split_into_its_results_coming_and_their_reading(in_flight, ready, read):
    """``frame_ms``: from submit to the last head's result there, and from then or the wait call, whichever is
    later, to the wait's return."""
    engines = [Engine(0.0, ready=ready, read=read) for _ in range(2)]
    _, whole, _, spent = _all_cameras(
        [(e, None) for e in engines], [None], rounds=8, seconds=0.0, in_flight=in_flight, heads=HEADS
    )
    assert whole == 16 and len(spent["ready"]) == len(spent["read"]) == 16
    # seconds; sleeps only ever last longer. ready is the last head's: depth's result came 5 ms before seg's
    assert ready - 0.001 <= statistics.median(spent["ready"]) < 1
    # the bound leaves a busy machine 30 ms of oversleep, and sits well below what the time before the read adds
    assert read <= statistics.median(spent["read"]) < read + 0.03


PAGES = 2048


@pytest.mark.skipif(not __import__("os").path.isdir("/proc/self/task"), reason="reads /proc (Linux)")
def test_page_faults_are_counted_by_thread_name_and_by_worker_process():
    import mmap
    import os
    import subprocess
    import sys
    import threading

    import numpy as np

    from vpengine.bench.cameras import _faults_between, _page_faults

    touch, touched, done = threading.Event(), threading.Event(), threading.Event()

    def toucher() -> None:
        touch.wait(10)
        buf = mmap.mmap(-1, PAGES * mmap.PAGESIZE)  # memory never touched before, in small pages: a fault a page
        if hasattr(mmap, "MADV_NOHUGEPAGE"):
            buf.madvise(mmap.MADV_NOHUGEPAGE)
        np.frombuffer(buf, np.uint8)[:: mmap.PAGESIZE] = 1
        touched.set()
        done.wait(10)
        buf.close()

    t = threading.Thread(target=toucher, name="toucher")
    t.start()
    child = subprocess.Popen(
        [sys.executable, "-c", "import sys; print('up', flush=True); sys.stdin.read()"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
    )
    try:
        assert child.stdout is not None and child.stdout.readline() == b"up\n"  # its start's faults are behind it
        workers = {child.pid: ["depth", "seg"], os.getpid(): ["foundation"]}  # this process's threads come by name
        before = _page_faults(workers)
        touch.set()
        assert touched.wait(10)
        taken = _faults_between(before, _page_faults(workers))
        assert taken.get("toucher", 0) >= 0.75 * PAGES, taken
        assert next(iter(taken)) == "toucher"  # most first
        assert "process depth+seg" in before and "process foundation" not in before
    finally:
        done.set()
        t.join()
        child.communicate(b"", timeout=10)
