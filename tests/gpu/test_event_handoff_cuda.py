"""Note [Event hand-off] on CUDA: in thread mode the foundation model publishes features whose device work is still
queued, and each head's stream waits on the slot's event. Run on the GPU machine: ``pytest -m gpu tests/gpu``.

The foundation's work is made slow on the device (the ``slow_foundation`` fixture of conftest.py) so that the heads are woken long before the features are there: a head that read without waiting would get the slot's previous frame.
The same engine with the wait taken out shows that this test sees that happen.
"""

from __future__ import annotations

import numpy as np
import pytest

from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine
from vpengine.runtime.device import DeviceContext

pytestmark = [pytest.mark.gpu, pytest.mark.timeout(900), pytest.mark.usefixtures("require_cuda")]


def run(handoff: str, n: int = 8) -> tuple[dict[int, dict[str, dict[str, np.ndarray]]], bool]:
    cfg = tiny("thread", "device=cuda", f"runtime.feature_handoff={handoff}")
    out = {}
    with Engine(cfg) as e:
        events = e._res.rings["features"].device_events
        for i in range(n):
            res = e.wait(e.submit(frame(i), frame_id=i), timeout=120)
            assert set(res) == {"depth", "seg", "det"}, (handoff, i, sorted(res))
            out[i] = {h: {k: np.array(v) for k, v in r.outputs.items()} for h, r in res.items()}
        assert all(m["errors"] == 0 for m in e.stats()["models"].values())
    return out, events is not None


def same(a, b) -> bool:  # type: ignore[no-untyped-def]
    return all(np.array_equal(a[i][h][k], b[i][h][k]) for i in a for h in a[i] for k in a[i][h])


def test_heads_read_features_handed_off_by_event_exactly_as_if_handed_off_on_the_host(slow_foundation):
    host, host_events = run("host")
    event, event_events = run("event")
    assert not host_events and event_events
    assert same(event, host)


def test_without_the_device_wait_the_heads_would_read_the_previous_frame(slow_foundation, monkeypatch):
    host, _ = run("host")
    monkeypatch.setattr(DeviceContext, "wait_on", lambda self, event: None)
    unordered, _ = run("event")
    assert not same(unordered, host)
