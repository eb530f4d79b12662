"""Note [Device sync]: how a worker waits for its device work, driven by stand-in events (CUDA's need a GPU; the
real ones are exercised in tests/gpu/test_engine_gpu.py)."""

from __future__ import annotations

import time

from vpengine.runtime.device import DeviceContext


class Work:
    """A stand-in CUDA event over work that takes ``seconds`` from its record; notes when each wait began."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.waits: list[float] = []  # when each synchronize() began, as time before the work is done
        self.done_at = 0.0

    def record(self, stream: object) -> None:
        self.done_at = time.monotonic() + self.seconds

    def query(self) -> bool:
        return time.monotonic() >= self.done_at

    def synchronize(self) -> None:
        self.waits.append(self.done_at - time.monotonic())
        time.sleep(max(0.0, self.done_at - time.monotonic()))


def context(spin_s: float, seconds: float) -> tuple[DeviceContext, Work, Work]:
    """A context whose sleeping and spinning events stand in for work of ``seconds``."""
    dev = DeviceContext("cpu", spin_s=spin_s)
    sleeping, spinning = Work(seconds), Work(seconds)
    dev.stream, dev.event = object(), sleeping  # type: ignore[assignment]
    dev.spin_event = spinning if spin_s > 0 else None  # type: ignore[assignment]
    return dev, sleeping, spinning


def done(*works: Work) -> bool:
    return all(time.monotonic() >= w.done_at for w in works)


def test_without_a_spin_window_the_worker_only_sleeps_in_the_driver():
    dev, sleeping, _ = context(0.0, 0.005)
    assert dev.spin_event is None
    for _ in range(3):
        dev.complete()
        assert done(sleeping)
    assert len(sleeping.waits) == 3


# Windows of a few ms, not the 0.1-0.2 ms a GPU wants: on a loaded 2-core CI machine a sleep can wake a few ms
# late, and a spin that outlasts its window by twice the window (here 10 ms) makes the next run relearn.
WINDOW = 0.005


def test_with_a_spin_window_it_sleeps_through_the_predicted_part_and_spins_only_the_end():
    dev, sleeping, spinning = context(WINDOW, 0.030)
    dev.complete()  # nothing predicted yet: a sleeping wait, which teaches it the 30 ms
    assert done(sleeping) and len(sleeping.waits) == 1 and not spinning.waits
    assert 0.029 < dev.expected_s < 0.040
    for _ in range(10):
        dev.complete()
        assert done(spinning)
    assert len(sleeping.waits) == 1 and len(spinning.waits) == 10
    # each spin began at most about the window before the work was done (late only by the sleep's wake-up)
    assert max(spinning.waits) < WINDOW + 0.002, [round(w * 1e3, 2) for w in spinning.waits]
    assert 0.025 < dev.expected_s < 0.040


def test_a_run_slower_than_predicted_is_spun_through_once_then_the_next_sleeps_and_relearns():
    dev, sleeping, spinning = context(WINDOW, 0.010)
    for _ in range(20):
        dev.complete()
    assert len(sleeping.waits) == 1 and len(spinning.waits) == 19
    sleeping.seconds = spinning.seconds = 0.100  # a sudden slow frame, and the ones after it
    dev.complete()
    assert done(spinning) and spinning.waits[-1] > 0.080  # spun through: it could not know
    dev.complete()  # the spin outlasted its window: this one sleeps, and learns the new time from it
    assert done(sleeping) and len(sleeping.waits) == 2 and len(spinning.waits) == 20
    assert 0.099 < dev.expected_s < 0.115
    for _ in range(3):  # and the runs after it spin again, only at the end
        dev.complete()
    assert len(sleeping.waits) == 2 and max(spinning.waits[-3:]) < WINDOW + 0.002
