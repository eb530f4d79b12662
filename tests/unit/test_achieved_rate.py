"""A model's achieved rate over several cameras (``ControlBlock.snapshot`` with its camera entries): each camera's
own rate, summed. Pooled, two cameras' frames of one tick, started microseconds apart, read as a billion Hz (a head
added at run time, after a pause) on /diagnostics, the live view and Prometheus."""

from __future__ import annotations

import time

import pytest

from vpengine.runtime.control import ControlBlock


@pytest.fixture()
def ctl():
    c = ControlBlock.create(["depth", "depth@front", "depth@rear"])
    yield c
    c.close()


def test_one_tick_of_two_cameras_is_no_rate_and_steady_cameras_sum(ctl):
    now = time.monotonic()
    for cam in ("front", "rear"):  # one frame each, a microsecond apart
        ctl.record_run(f"depth@{cam}", now - 0.1 + (1e-6 if cam == "rear" else 0.0), 0.01, 0.02, 0)
    snap = ctl.snapshot("depth", cameras=["depth@front", "depth@rear"])
    assert snap["achieved_hz"] == 0.0  # one start a camera: no rate yet, not 1e6 Hz
    for k in range(1, 11):  # then each camera at 10 Hz over one second
        for cam in ("front", "rear"):
            ctl.record_run(f"depth@{cam}", now - 0.1 - k * 0.1, 0.01, 0.02, k)
    snap = ctl.snapshot("depth", cameras=["depth@front", "depth@rear"])
    assert snap["achieved_hz"] == pytest.approx(20.0, rel=0.01)
