"""``runtime.wait_spin_us`` (Note [Device sync], the caller's hop): ``Engine.wait`` sleeps through the part of a wait
its recent waits predict and polls only the end, where the last head's result comes; a frame slower than predicted
ends in the sleeping wait. The latency it saves is measured on the GPU (benchmarks/gpu/profile_steps.py)."""

from __future__ import annotations

import time

import pytest

from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine

pytestmark = pytest.mark.timeout(120)
SLOW = "heads.depth.model=helpers.faulty:FaultyHead"


class Trace:
    """Wraps the control block's output word: what each ``wait`` did, in order ('sleep' or 'poll')."""

    def __init__(self, e: Engine) -> None:
        ctl = e._res.control
        self.events: list[str] = []
        read, sleep = ctl.output_word, ctl.wait_output

        def output_word() -> int:
            self.events.append("poll")
            return read()

        def wait_output(word: int, timeout: float) -> None:
            self.events.append("sleep")
            sleep(word, timeout)

        ctl.output_word, ctl.wait_output = output_word, wait_output

    def wait(self, e: Engine, i: int) -> tuple[list[str], float]:
        """Submit frame ``i`` and wait for it: (what the wait did, the calling thread's CPU seconds in it)."""
        fid = e.submit(frame(i), frame_id=i)
        self.events.clear()
        cpu0 = time.thread_time()
        res = e.wait(fid, timeout=10)
        cpu = time.thread_time() - cpu0
        assert set(res) == {"depth", "seg", "det"} and all(r.frame_id == i for r in res.values())
        return list(self.events), cpu


def ends_polling(events: list[str]) -> bool:
    """The last head's result was seen by polling: the wait's last sleep came before its last polls."""
    return events[-2:] == ["poll", "poll"]


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_the_caller_sleeps_through_the_predicted_wait_and_polls_only_its_end(mode):
    overrides = ["runtime.wait_spin_us=3000", SLOW, 'heads.depth.options={"sleep_ms": 40}']
    with Engine(tiny(mode, *overrides)) as e:
        for i in range(25):  # the prediction (a moving average) learns the 40 ms
            e.wait(e.submit(frame(i), frame_id=i), timeout=10)
        assert 0.035 < e._wait_spin.expected_s < 0.2, e._wait_spin.expected_s
        trace = Trace(e)
        waits = [trace.wait(e, i) for i in range(25, 35)]
    caught = sum(ends_polling(ev) for ev, _ in waits)
    assert caught >= 7, [ev[-4:] for ev, _ in waits]
    assert all("sleep" in ev for ev, _ in waits)  # slept through the predicted part
    cpu = sorted(c for _, c in waits)
    # polling takes at most twice the 3 ms window; spinning through the whole 40 ms would take ~40 ms
    assert cpu[len(cpu) // 2] < 0.015, (
        f"the caller used {cpu[len(cpu) // 2] * 1e3:.1f} ms of CPU in a 40 ms wait"
    )


def test_without_a_spin_window_the_caller_only_sleeps():
    with Engine(tiny("thread", SLOW, 'heads.depth.options={"sleep_ms": 20}')) as e:
        for i in range(5):
            e.wait(e.submit(frame(i), frame_id=i), timeout=10)
        trace = Trace(e)
        waits = [trace.wait(e, i) for i in range(5, 10)]
    for ev, _ in waits:  # one look at the word per sleep, none in between
        assert ev.count("poll") == ev.count("sleep") + 1 and not ends_polling(ev), ev


def test_a_frame_slower_than_predicted_ends_in_the_sleeping_wait():
    slow = '{"sleep_ms": 10, "stall_every": 30, "stall_ms": 150}'  # run 30 (frame 29) stalls
    with Engine(tiny("thread", "runtime.wait_spin_us=2000", SLOW, f"heads.depth.options={slow}")) as e:
        for i in range(29):
            e.wait(e.submit(frame(i), frame_id=i), timeout=10)
        trace = Trace(e)
        t0 = time.monotonic()
        events, cpu = trace.wait(e, 29)
        took = time.monotonic() - t0
    assert took > 0.15
    assert not ends_polling(events), events[
        -6:
    ]  # gave up polling after 2 x 2 ms, slept until the result came
    assert cpu < 0.05, f"the caller used {cpu * 1e3:.1f} ms of CPU in a {took * 1e3:.0f} ms wait"
