"""Note [Event hand-off] and Note [Result hand-off] on CUDA: in thread mode the foundation model publishes features
whose device work is still queued, and each head's stream waits on the slot's event; each head publishes results
whose device work (and copy to the host) is still queued, and the engine waits on the slot's event before it reads.
Run on the GPU machine: ``pytest -m gpu tests/gpu``.

The reference is the same engine in process mode, where every hop is handed over on the host. The model whose
hand-off is tested is made slow on the device (the ``slow_foundation`` and ``slow_heads`` fixtures
of conftest.py), so its readers are woken long before its slots are written: a reader that did not wait would get
the slot's previous content. The same engine with the wait taken out shows that these tests see that happen.
"""

from __future__ import annotations

import numpy as np
import pytest

from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine
from vpengine.runtime import handoff
from vpengine.runtime.device import DeviceContext
from vpengine.runtime.handoff import SlotEvents

pytestmark = [pytest.mark.gpu, pytest.mark.timeout(900), pytest.mark.usefixtures("require_cuda")]

HEADS = {"depth", "seg", "det"}
Outputs = dict[int, dict[str, dict[str, np.ndarray]]]


def arrays(r) -> dict[str, np.ndarray]:  # type: ignore[no-untyped-def]
    return {k: np.array(v) for k, v in r.outputs.items()}


def run(mode: str, n: int = 8, copy: bool = True) -> tuple[Outputs, dict[str, bool], list[float]]:
    """n frames one at a time through Engine.wait: outputs, which rings hand off by event, every result's latency."""
    cfg = tiny(mode, "device=cuda")
    out, latencies = {}, []
    with Engine(cfg) as e:
        for i in range(n):
            res = e.wait(e.submit(frame(i), frame_id=i), timeout=120, copy=copy)
            assert set(res) == HEADS, (mode, i, sorted(res))
            out[i] = {h: arrays(r) for h, r in res.items()}
            latencies += [r.latency for r in res.values()]
        assert all(m["errors"] == 0 for m in e.stats()["models"].values())
        events = {"features": e._handoffs.features is not None}
        events.update({f"out.{h}": h in e._handoffs.results for h in HEADS})
    return out, events, latencies


def same(a, b) -> bool:  # type: ignore[no-untyped-def]
    return all(np.array_equal(a[i][h][k], b[i][h][k]) for i in a for h in a[i] for k in a[i][h])


def test_heads_read_features_handed_off_by_event_exactly_as_if_handed_off_on_the_host(slow_foundation):
    host, host_events, _ = run("process")
    event, event_events, _ = run("thread")
    assert not host_events["features"] and event_events["features"]
    assert same(event, host)


def test_without_the_device_wait_the_heads_would_read_the_previous_frame(slow_foundation, monkeypatch):
    host, _, _ = run("process")
    monkeypatch.setattr(DeviceContext, "wait_on", lambda self, event: None)
    unordered, _, _ = run("thread")
    assert not same(unordered, host)


@pytest.mark.parametrize(
    "copy, spin", [(True, 200), (False, 200), (True, 0)], ids=["copied", "borrowed", "copied-no-wait-spin"]
)
def test_results_handed_off_by_event_reach_the_caller_exactly_as_if_handed_off_on_the_host(
    slow_heads, monkeypatch, copy, spin
):
    host, host_events, host_latency = run("process", copy=copy)
    monkeypatch.setattr(handoff, "WAIT_SPIN_S", spin * 1e-6)
    event, event_events, event_latency = run("thread", copy=copy)
    assert not any(host_events[f"out.{h}"] for h in HEADS)
    assert all(event_events[f"out.{h}"] for h in HEADS)
    assert same(event, host)
    # each head's work sleeps a few ms on the device after it is published: a result's latency is when it was
    # there, not when it was published
    assert min(event_latency) > 1e-3 and min(host_latency) > 1e-3, (min(event_latency), min(host_latency))


def test_without_waiting_for_the_device_the_caller_would_read_an_older_result(slow_heads, monkeypatch):
    host, _, _ = run("process")
    monkeypatch.setattr(SlotEvents, "wait_done", lambda self, slot, spin_s=None: slot.t_publish)
    unordered, _, _ = run("thread")
    assert not same(unordered, host)


def test_results_and_latest_give_only_results_whose_device_work_is_done(slow_heads):
    host, _, _ = run("process", n=6)
    cfg = tiny("thread", "device=cuda")
    with Engine(cfg) as e:
        e.results()  # starts the stream
        for i in range(6):
            fid = e.submit(frame(i), frame_id=i)
            got: dict[str, np.ndarray] = {}
            while set(got) != HEADS:
                for r in e.results(timeout=30):
                    assert r.frame_id == fid and r.head not in got, (r.head, r.frame_id, fid)
                    got[r.head] = arrays(r)
                    assert all(np.array_equal(got[r.head][k], host[i][r.head][k]) for k in got[r.head]), (
                        i,
                        r.head,
                    )
                    latest = e.latest(r.head)  # the newest that is there: this frame's (the next is not submitted)
                    assert latest is not None and latest.frame_id == fid, (r.head, latest)
        assert all(r["missed"] == 0 and r["delivered"] == 6 for r in e.stats()["results"].values())


def test_a_wait_does_not_sit_in_the_driver_past_its_timeout_for_a_result_due_later(very_slow_heads):
    import time

    cfg = tiny("thread", "device=cuda")
    with Engine(cfg) as e:
        for i in range(3):  # the heads' results teach the engine how long their work takes (about 0.1 s)
            e.wait(e.submit(frame(i), frame_id=i), timeout=120)
        fid = e.submit(frame(3), frame_id=3)
        time.sleep(0.02)  # every head has published its queued results by now
        t0 = time.monotonic()
        with pytest.raises(TimeoutError):
            e.wait(fid, timeout=0.01)
        took = time.monotonic() - t0
        assert took < 0.05, f"waited {took * 1e3:.0f} ms for a 10 ms timeout"
        res = e.wait(fid, timeout=120)
        assert set(res) == HEADS and all(r.latency > 0.09 for r in res.values())


def test_the_default_wait_polls_for_each_result_near_its_predicted_end_and_catches_it(slow_heads, monkeypatch):
    caught: list[bool] = []
    poll = handoff.poll

    def counted(*a):  # type: ignore[no-untyped-def]
        caught.append(poll(*a))
        return caught[-1]

    monkeypatch.setattr(handoff, "poll", counted)
    host, _, _ = run("process", n=20)
    event, _, _ = run("thread", n=20)
    assert same(event, host)
    # every head's work takes the same few ms on the device, so the prediction holds: the poll, not the driver,
    # sees the results done (a wait that finds its result already done does not poll)
    assert len(caught) >= 10 and sum(caught) >= 0.8 * len(caught), caught
