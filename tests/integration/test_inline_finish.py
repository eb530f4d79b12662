"""Note [Inline finish]: in thread mode a head hands its run of a frame to the thread waiting for that frame in
``Engine.wait``, which waits for the work and publishes the output itself. On the CPU (``runtime.inline_finish:
always``; ``auto`` uses it only on CUDA) the work is done when it is handed over; the CUDA path runs in these tests
with VPENGINE_TEST_DEVICE=cuda and in the floor benchmark."""

from __future__ import annotations

import numpy as np
import pytest

from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine

pytestmark = pytest.mark.timeout(120)
HEADS = ("depth", "seg", "det")


def lockstep(e: Engine, n: int, stream: list | None = None) -> dict[int, dict[str, dict[str, np.ndarray]]]:
    """n frames one at a time; ``stream`` collects ``Engine.results`` after each."""
    out = {}
    for i in range(n):
        res = e.wait(e.submit(frame(i), frame_id=i), timeout=10)
        assert set(res) == set(HEADS) and all(r.frame_id == i for r in res.values())
        out[i] = {h: {k: np.array(v) for k, v in r.outputs.items()} for h, r in res.items()}
        if stream is not None:
            stream += e.results(timeout=0.5)
    return out


def finishes(e: Engine) -> dict[str, int | None]:
    return {h: (f.finishes if (f := e._res.rings[f"out.{h}"].finish) else None) for h in HEADS}


def test_the_waiting_thread_publishes_every_heads_run_once_with_the_same_outputs():
    n = 20
    with Engine(tiny("thread", "runtime.inline_finish=never")) as e:
        want = lockstep(e, n)
        assert finishes(e) == dict.fromkeys(HEADS)
    with Engine(tiny("thread", "runtime.inline_finish=always")) as e:
        stream: list = e.results()  # starts the results stream: every output published from here on
        assert stream == []
        got = lockstep(e, n, stream)
        handed = finishes(e)
        models = e.stats()["models"]
    # A run is handed over only if the waiting thread got into wait() before the head queued it: on the CPU most
    # are; the others were published by their workers. Either way each output is published once, the same.
    assert all(n // 2 <= handed[h] <= n for h in HEADS), handed
    for i in range(n):
        for h in HEADS:
            for k, v in want[i][h].items():
                np.testing.assert_array_equal(got[i][h][k], v, err_msg=f"frame {i} {h}.{k}")
    per_head = {h: sorted(r.frame_id for r in stream if r.head == h) for h in HEADS}
    assert per_head == {h: list(range(n)) for h in HEADS}, per_head  # each published exactly once
    for h in HEADS:
        assert models[h]["runs"] == n and models[h]["dropped"] == 0, models[h]
        assert models[h]["latency_ms"]["p50"] > 0  # counted as its worker counts it


def test_heads_nobody_waits_for_publish_from_their_own_threads():
    with Engine(tiny("thread", "runtime.inline_finish=always")) as e:
        for i in range(5):
            res = e.wait(e.submit(frame(i), frame_id=i), heads=["depth"], timeout=10)
            assert set(res) == {"depth"} and res["depth"].frame_id == i
            rest = e.wait(i, heads=["seg", "det"], timeout=10)  # published by their workers meanwhile
            assert {h: r.frame_id for h, r in rest.items()} == {"seg": i, "det": i}
        handed = finishes(e)
    assert handed["depth"] == 5, handed
    assert handed["seg"] + handed["det"] < 10, handed  # mostly published before the second wait began
