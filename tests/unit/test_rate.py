"""The rate gate, driven through a simulation of the worker loop with a fake clock (no sleeping)."""

from __future__ import annotations

import math

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
) -> list[float]:
    """Run the worker's gate logic against frames arriving at ``input_hz``; return run start times.

    ``rates`` is a schedule of (from_time, hz) changes, as set_rate would make them.
    """
    gate = RateGate()
    n = int((duration - first_frame_at) * input_hz)
    frames = [first_frame_at + k / input_hz + (jitter * ((k * 7919) % 13) / 13 if k else 0) for k in range(n)]
    if random_jitter:  # a backbone whose latency varies: frames reach the head a random few ms late
        import numpy as np

        late = np.random.default_rng(7).uniform(0, random_jitter, n)
        frames = sorted(f + d for f, d in zip(frames, late))
    seen = -1  # index of the last frame the worker took
    starved = False
    t = 0.0
    starts = []
    while t < duration:
        hz = [h for t0, h in rates if t0 <= t][-1]
        gate.update(hz, t)
        wait = gate.wait_time(t)
        if math.isinf(wait):
            nxt = min([t0 for t0, _ in rates if t0 > t], default=duration)
            t = nxt
            continue
        if wait > 0:
            changes = [t0 for t0, _ in rates if t < t0 < t + wait]
            t = changes[0] if changes else t + wait
            continue
        newest = max((k for k, ft in enumerate(frames) if ft <= t), default=-1)
        if newest <= seen:  # wait for the next frame
            if seen + 1 >= len(frames):
                break
            t = frames[seen + 1]
            starved = True
            continue
        seen = newest
        t += busy(t)  # the OS may not run us right away
        gate.started(t, starved)
        starved = False
        starts.append(t)
        t += compute_s
    return starts


@pytest.mark.parametrize("hz", [1, 5, 7, 10, 15, 20, 29.97])
def test_rate_gives_r_times_n_plus_minus_one(hz):
    runs = simulate([(0.0, hz)])
    assert abs(len(runs) - hz * 10) <= 1, f"{len(runs)} runs at {hz} Hz over 10 s"


@pytest.mark.parametrize("hz", [5, 10, 20])
def test_rate_holds_with_jittery_input(hz):
    runs = simulate([(0.0, hz)], jitter=0.012)
    assert abs(len(runs) - hz * 10) <= 1


@pytest.mark.parametrize("hz", [5, 10, 20])
@pytest.mark.parametrize("first", [1.0, 0.1, 0.03])  # gate set at start, first frame a while later
def test_rate_holds_when_the_first_frame_comes_after_start(hz, first):
    runs = simulate([(0.0, hz)], duration=10.0 + first, first_frame_at=first)
    assert abs(len(runs) - hz * 10) <= 1
    assert runs[1] - runs[0] >= 1 / hz - 1e-9  # no early second run


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
    assert not [
        r for r in runs if 3.0 + 1 / 10 <= r < 6.0
    ]  # paused (one in-flight run allowed at the switch)
    resumed = [r for r in runs if r >= 6.0]
    assert resumed[0] - 6.0 < 1 / 30 + 1e-9  # runs on the next frame
    assert abs(len(resumed) - 30) <= 1


def test_no_catch_up_burst_after_an_idle_spell():
    gate = RateGate()
    gate.update(10.0, 0.0)
    gate.started(0.0)
    # nothing to do for 5 s, then frames every 33 ms: at most one early run, then 10 Hz again
    starts = []
    t = 5.0
    while t < 7.0:
        if gate.wait_time(t) == 0:
            gate.started(t)
            starts.append(t)
        t += 1 / 30
    assert abs(len(starts) - 20) <= 1


@pytest.mark.parametrize("hz", [29.97, 30.0])
def test_a_limit_equal_to_the_input_rate_loses_no_frames_when_they_arrive_late(hz):
    # frames often land a few ms after the gate opens (the backbone's latency varies): the schedule must not drift
    runs = simulate([(0.0, hz)], random_jitter=0.012)
    assert len(runs) >= 299, len(runs)
