"""An idle engine sleeps: no busy-spinning while there is no input."""

from __future__ import annotations

import time

import psutil
import pytest

from tests_paths import tiny
from vpengine.engine import Engine

pytestmark = pytest.mark.timeout(60)


def cpu_seconds(procs: list[psutil.Process]) -> float:
    total = 0.0
    for p in procs:
        t = p.cpu_times()
        total += t.user + t.system
    return total


@pytest.mark.parametrize("mode", ["process", "thread"])
def test_idle_engine_uses_under_5_percent_of_one_core(mode):
    with Engine(tiny(mode)) as e:
        procs = [psutil.Process()] + [
            psutil.Process(m["pid"]) for m in e.stats()["models"].values() if m["pid"] != psutil.Process().pid
        ]
        time.sleep(1.0)  # let start-up settle
        c0, t0 = cpu_seconds(procs), time.monotonic()
        time.sleep(2.5)  # a busy-spinning wait shows in any window: 5% of 2.5 s is 0.125 s, 12 clock ticks
        used = (cpu_seconds(procs) - c0) / (time.monotonic() - t0)
    assert used < 0.05, f"idle engine used {used:.1%} of one core"
