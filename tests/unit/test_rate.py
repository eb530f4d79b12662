"""The rate gate, driven through a simulation of the worker loop on the frames' own clock (no sleeping)."""

from __future__ import annotations

import pytest

from vpengine.runtime.rate import RateGate


def simulate(
    rates: list[tuple[float, float | None]],
    input_hz: float = 30.0,
    duration: float = 10.0,
    compute_s: float = 0.004,
    jitter: float = 0.0,
    first_frame_at: float = 0.0,
    busy=lambda t: 0.0,
    random_jitter: float = 0.0,
    speed: float = 1.0,
) -> list[float]:
    """Offer the gate the frames a worker would take, as the worker loop does; return the admitted frames' stamps.

    Frames are stamped ``k / input_hz`` (plus jitter) on the source's clock and reach the worker ``speed`` times
    faster than real time (a file read in lockstep: many times faster). ``rates`` is a schedule of (from frame time,
    hz) changes, as set_rate would make them.
    """
    gate = RateGate()
    n = int((duration - first_frame_at) * input_hz)
    stamps = [first_frame_at + k / input_hz + (jitter * ((k * 7919) % 13) / 13 if k else 0) for k in range(n)]
    if random_jitter:  # stamps a random few ms late (a camera driver's jitter)
        import numpy as np

        late = np.random.default_rng(7).uniform(0, random_jitter, n)
        stamps = sorted(f + d for f, d in zip(stamps, late))
    arrive = [s / speed for s in stamps]
    seen = -1  # index of the last frame the worker took
    t = 0.0  # the worker's clock
    runs = []
    while seen + 1 < n:
        newest = max((k for k, a in enumerate(arrive) if a <= t), default=-1)
        if newest <= seen:  # wait for the next frame
            t = arrive[seen + 1]
            continue
        missed, seen = newest - seen - 1, newest
        stamp = stamps[newest]
        gate.update([h for t0, h in rates if t0 <= stamp][-1])
        if gate.admit(stamp, t, missed):
            runs.append(stamp)
            t += busy(t) + compute_s / speed  # the OS may not run us right away
    return runs


@pytest.mark.parametrize("hz", [1, 5, 7, 10, 15, 20, 29.97])
def test_rate_gives_r_times_n_plus_minus_one(hz):
    runs = simulate([(0.0, hz)])
    assert abs(len(runs) - hz * 10) <= 1, f"{len(runs)} runs at {hz} Hz over 10 s"


@pytest.mark.parametrize("hz", [1, 5, 7, 20])
def test_the_rate_is_on_the_source_clock_however_fast_frames_come(hz):
    # a file read 50x faster than real time gives the same runs as in real time
    assert simulate([(0.0, hz)], speed=50.0) == simulate([(0.0, hz)])


def test_half_the_input_rate_runs_every_second_frame():
    runs = simulate([(0.0, 5.0)], input_hz=10.0, duration=20.0, speed=100.0)
    assert [round(r * 10) for r in runs] == list(range(0, 200, 2))


@pytest.mark.parametrize("hz", [5, 10, 20])
def test_rate_holds_with_jittery_input(hz):
    runs = simulate([(0.0, hz)], jitter=0.012)
    assert abs(len(runs) - hz * 10) <= 1


@pytest.mark.parametrize("hz", [5, 10, 20])
@pytest.mark.parametrize("first", [1.0, 0.1, 0.03])  # gate set at start, first frame a while later
def test_rate_holds_when_the_first_frame_comes_after_start(hz, first):
    runs = simulate([(0.0, hz)], duration=10.0 + first, first_frame_at=first)
    assert abs(len(runs) - hz * 10) <= 1
    assert runs[1] - runs[0] >= 1 / hz - 1 / 60  # no early second run (half a frame early at most)


@pytest.mark.parametrize("hz", [5, 10, 20])
def test_a_loaded_cpu_that_delays_runs_by_more_than_a_period_loses_no_runs(hz):
    # every 7th run is descheduled for 1.5 periods: the schedule must catch up, not restart
    count = {"n": 0}

    def busy(t):
        count["n"] += 1
        return 1.5 / hz if count["n"] % 7 == 0 else 0.0

    runs = simulate([(0.0, hz)], busy=busy)
    assert abs(len(runs) - hz * 10) <= 1, len(runs)


def test_unlimited_runs_every_frame_and_above_input_rate_is_input_bound():
    assert len(simulate([(0.0, None)])) == 300
    assert len(simulate([(0.0, 60.0)])) == 300


def test_change_takes_effect_within_one_period():
    runs = simulate([(0.0, 5.0), (4.0, 20.0)], duration=8.0)
    before = [r for r in runs if r < 4.0]
    after = [r for r in runs if r >= 4.0]
    assert abs(len(before) - 20) <= 1 and abs(len(after) - 80) <= 1
    assert after[0] - 4.0 <= 1 / 5.0  # first run at the new rate within one old period


def test_zero_pauses_and_a_new_rate_resumes_at_once():
    runs = simulate([(0.0, 10.0), (3.0, 0.0), (6.0, 10.0)], duration=9.0)
    assert not [r for r in runs if 3.0 <= r < 6.0]
    resumed = [r for r in runs if r >= 6.0]
    assert resumed[0] - 6.0 < 1 / 30 + 1e-9  # runs on the next frame
    assert abs(len(resumed) - 30) <= 1


def test_no_catch_up_burst_after_an_idle_spell():
    gate = RateGate()
    gate.update(10.0)
    assert gate.admit(0.0, 0.0)
    # nothing for 5 s, then frames every 33 ms: 10 Hz again, no burst of the 50 runs the gap "owed"
    starts = [t for t in (5.0 + k / 30 for k in range(60)) if gate.admit(t, t)]
    assert abs(len(starts) - 20) <= 1
    assert starts[1] - starts[0] >= 0.1 - 1 / 60


def test_stamps_that_go_back_move_the_clock_on_by_arrival_not_back():
    gate = RateGate()
    gate.update(1.0)
    assert gate.admit(100.0, 0.0)
    assert not gate.admit(100.5, 0.5)
    assert gate.admit(0.0, 1.0)  # the file played again from its start, a second after its first frame
    assert not gate.admit(0.5, 1.5)
    assert gate.admit(1.0, 2.0)


@pytest.mark.parametrize("stamp", [lambda k: 0.0, lambda k: 42.0 - k])  # all zero, or running backwards
def test_stamps_that_do_not_advance_fall_back_to_the_arrival_clock(stamp):
    # a driver that stamps badly must not stop a rate-limited model for good: 30 Hz arrivals, 5 Hz limit
    gate = RateGate()
    gate.update(5.0)
    runs = sum(gate.admit(stamp(k), k / 30, 0) for k in range(300))
    assert abs(runs - 50) <= 1


@pytest.mark.parametrize("hz", [29.97, 30.0])
def test_a_limit_equal_to_the_input_rate_loses_no_frames_when_they_arrive_late(hz):
    # stamps often land a few ms late: the schedule must not drift
    runs = simulate([(0.0, hz)], random_jitter=0.012)
    assert len(runs) >= 299, len(runs)
