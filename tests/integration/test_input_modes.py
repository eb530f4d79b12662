"""A head's input mode: `latest` skips to the newest frame after a lag, `fifo` catches up on every frame in order."""

from __future__ import annotations

import json
import time

import pytest

from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine

pytestmark = pytest.mark.timeout(120)
FAULTY = "helpers.faulty:FaultyHead"


@pytest.mark.parametrize("mode", ["process", "thread"])
def test_a_fifo_head_catches_up_on_every_frame_where_a_latest_head_skips(mode):
    stall = json.dumps({"stall_every": 10, "stall_ms": 75})  # every 10th run lags ~3 frames behind
    cfg = tiny(
        mode,
        f"heads.seg.model={FAULTY}",
        f"heads.seg.options={stall}",
        "heads.seg.input_mode=fifo",
        "foundation_model.input_mode=fifo",  # every frame's features, however busy the machine: what seg needs
        f"heads.depth.model={FAULTY}",
        f"heads.depth.options={stall}",
        "heads.seg.output.slots=128",
        "heads.depth.output.slots=128",
    )
    n = 60
    with Engine(cfg) as e:
        e.results()  # start the results stream
        got: dict[str, list[int]] = {"seg": [], "depth": []}
        for i in range(n):
            e.submit(frame(i), frame_id=i)
            time.sleep(0.025)  # 40 Hz, well within every model's pace except during a stall
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and len(got["seg"]) < n:
            for r in e.results(timeout=0.2, heads=["seg", "depth"]):
                got[r.head].append(r.frame_id)
        for r in e.results(timeout=0.5, heads=["seg", "depth"]):
            got[r.head].append(r.frame_id)
        st = e.stats()["models"]
    assert st["foundation"]["skipped"] == 0, st["foundation"]
    assert got["seg"] == list(range(n)), f"fifo head: {got['seg']}"
    assert st["seg"]["skipped"] == 0 and st["seg"]["runs"] == n, st["seg"]
    # the same stalls make the latest-mode head skip ahead: the skips are counted and the frames it ran are in order
    assert st["depth"]["skipped"] > 0, f"{st['depth']} {got['depth']}"
    assert st["depth"]["runs"] + st["depth"]["skipped"] == n, st["depth"]
    assert got["depth"] == sorted(got["depth"]) and len(got["depth"]) == st["depth"]["runs"]


def test_fifo_models_get_mailboxes_with_room_to_catch_up():
    def sizes(*overrides):
        with Engine(tiny("thread", *overrides)) as e:
            return e._res.rings["input"].n_slots, e._res.rings["features"].n_slots

    assert sizes("runtime.spare_heads=0") == (3, 5)  # latest everywhere: the minimum, readers + 2
    assert sizes() == (3, 6)  # and a slot for the spare seat's reader (Note [Heads at run time])
    fifo = ("foundation_model.input_mode=fifo", "heads.seg.input_mode=fifo")
    assert sizes("runtime.spare_heads=0", *fifo) == (7, 9)
