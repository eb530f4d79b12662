"""Rate limits over real processes: R Hz for N seconds of 30 Hz input gives R*N +-1 runs; changes, pause, resume."""

from __future__ import annotations

import time

import pytest

from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine

pytestmark = pytest.mark.timeout(120)


def feed(engine: Engine, seconds: float, hz: float = 30.0, start: int = 0) -> int:
    """Submit frames at ``hz`` on a fixed schedule for ``seconds``; returns how many."""
    imgs = [frame(i) for i in range(4)]
    t0 = time.monotonic()
    n = 0
    while True:
        t = t0 + n / hz
        if t - t0 >= seconds:
            break
        delay = t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        engine.submit(imgs[(start + n) % 4])
        n += 1
    return n


def runs(engine: Engine) -> dict[str, int]:
    return {n: m["runs"] for n, m in engine.stats()["models"].items()}


def test_heads_at_5_10_20_hz_over_10_s_of_30_hz_input():
    cfg = tiny("process", "heads.depth.rate_hz=5", "heads.seg.rate_hz=10", "heads.det.rate_hz=20")
    with Engine(cfg) as e:
        n = feed(e, 10.0)
        time.sleep(0.3)
        got = runs(e)
        st = e.stats()["models"]
    assert n == 300
    assert got["foundation"] >= 295, got  # the backbone keeps up with 30 Hz
    for head, hz in (("depth", 5), ("seg", 10), ("det", 20)):
        assert abs(got[head] - hz * 10) <= 1, f"{head}: {got[head]} runs at {hz} Hz over 10 s"
        assert st[head]["runs"] + st[head]["skipped"] + st[head]["dropped"] == st[head]["frames_seen"]


def test_rate_change_pause_and_resume_while_running():
    cfg = tiny("process", "heads.depth.rate_hz=10")
    with Engine(cfg) as e:
        r0 = runs(e)["depth"]
        feed(e, 3.0)
        r1 = runs(e)["depth"]
        e.set_rate("depth", 20)
        feed(e, 3.0, start=90)
        r2 = runs(e)["depth"]
        assert abs(e.stats()["models"]["depth"]["achieved_hz"] - 20) < 3
        e.set_rate("depth", 0)
        time.sleep(0.1)
        paused_at = runs(e)["depth"]
        feed(e, 2.0, start=180)
        r3 = runs(e)["depth"]
        assert e.stats()["models"]["depth"]["state"] == "paused"
        e.set_rate("depth", 5)
        feed(e, 2.0, start=240)
        r4 = runs(e)["depth"]
        fm = runs(e)["foundation"]
    assert abs((r1 - r0) - 30) <= 2, r1 - r0  # 3 s at 10 Hz
    assert abs((r2 - r1) - 60) <= 2, r2 - r1  # 3 s at 20 Hz: the change took effect
    assert r3 - paused_at == 0, "a paused head ran"
    assert abs((r4 - r3) - 10) <= 2, r4 - r3  # resumed at 5 Hz
    assert fm >= 290  # the backbone was never held up by the head's rate
