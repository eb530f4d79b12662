"""Note [Device sync]: how a worker waits for its device work, driven by a stand-in event (CUDA's needs a GPU; the
real one is exercised in tests/gpu/test_engine_gpu.py)."""

from __future__ import annotations

import time

from vpengine.runtime.device import DeviceContext


class Work:
    """A stand-in CUDA event over work that takes ``seconds`` from its record."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.queries = self.syncs = 0
        self.done_at = 0.0

    def record(self, stream: object) -> None:
        self.done_at = time.monotonic() + self.seconds

    def query(self) -> bool:
        self.queries += 1
        return time.monotonic() >= self.done_at

    def synchronize(self) -> None:
        self.syncs += 1
        time.sleep(max(0.0, self.done_at - time.monotonic()))


def context(spin_s: float, work: Work) -> DeviceContext:
    dev = DeviceContext("cpu", spin_s=spin_s)
    dev.stream, dev.event = object(), work  # type: ignore[assignment]
    return dev


def test_without_a_spin_window_the_worker_only_sleeps_in_the_driver():
    work = Work(0.005)
    dev = context(0.0, work)
    for _ in range(3):
        dev.complete()
        assert time.monotonic() >= work.done_at
    assert work.syncs == 3 and work.queries == 0


def test_with_a_spin_window_it_sleeps_through_the_predicted_part_and_polls_only_the_end():
    work = Work(0.020)
    dev = context(0.002, work)
    dev.complete()  # nothing predicted yet: polls for at most 2 * 2 ms, then sleeps in the driver
    assert time.monotonic() >= work.done_at and work.syncs == 1
    for _ in range(30):  # the prediction learns the 20 ms
        dev.complete()
        assert time.monotonic() >= work.done_at
    assert 0.015 < dev.expected_s < 0.025
    work.queries = work.syncs = 0
    cpu0, wall0 = time.process_time(), time.monotonic()
    late = []
    for _ in range(10):
        dev.complete()
        late.append(time.monotonic() - work.done_at)
        assert late[-1] >= 0
    wall, cpu = time.monotonic() - wall0, time.process_time() - cpu0
    late.sort()
    assert late[5] < 0.001, f"returned {late[5] * 1e3:.2f} ms (median) after the work was done"
    assert work.syncs == 0  # caught by polling, never by the sleeping wait
    assert cpu < 0.5 * wall, f"{cpu:.3f} s of CPU in {wall:.3f} s: it spun instead of sleeping"


def test_work_longer_than_predicted_ends_in_the_sleeping_wait():
    work = Work(0.002)
    dev = context(0.001, work)
    for _ in range(20):
        dev.complete()
    work.seconds = 0.050  # a sudden slow frame
    work.queries = 0
    dev.complete()
    assert time.monotonic() >= work.done_at
    assert work.syncs >= 1  # gave up polling after 2 ms and slept
