"""The API's scalar arguments (frame ids, timestamps, timeouts, rates) are checked before the engine takes anything,
and a refused call leaves the engine serving (thread mode, one process)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch

from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine


@pytest.fixture(scope="module")
def engine():
    with Engine(tiny("thread")) as e:
        yield e


def input_slots_free(e: Engine) -> int:
    """Input slots neither written nor pinned: what submit can still take."""
    ring = e._res.rings["input"]
    with ring._mutex:
        return sum(ring._q[ring._slot(i)] != 1 for i in range(ring.n_slots))  # 1: WRITING


BAD_IDS = ["x", "7", 2**63, -(2**63) - 1, math.nan, 1.5, np.float64(3.0), True]


@pytest.mark.parametrize("bad", BAD_IDS, ids=[repr(b)[:12] for b in BAD_IDS])
def test_a_bad_frame_id_is_refused_before_a_slot_is_taken(engine, bad):
    slots = input_slots_free(engine)
    for _ in range(4):  # more than the input ring has slots: a leak would show as "no free slot"
        with pytest.raises(ValueError, match="frame_id must be"):
            engine.submit(frame(0), frame_id=bad)
        with pytest.raises(ValueError, match="frame_id must be"):
            engine.frame_slot(frame_id=bad)
    assert input_slots_free(engine) == slots
    fid = engine.submit(frame(1))
    assert set(engine.wait(fid, timeout=10)) == {"depth", "seg", "det"}


def test_numpy_and_int64_extreme_frame_ids_are_taken(engine):
    for fid in (np.int64(7), np.uint16(9), 2**63 - 2, -(2**63)):
        assert engine.submit(frame(2), frame_id=fid) == int(fid)
    assert engine.submit(frame(3)) == -(2**63) + 1  # the id after the last one given


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "now", True])
def test_nan_inf_and_non_number_timestamps_are_refused(engine, bad):
    slots = input_slots_free(engine)
    with pytest.raises(ValueError, match="timestamp must be None or a finite number"):
        engine.submit(frame(0), timestamp=bad)
    with pytest.raises(ValueError, match="timestamp must be None or a finite number"):
        engine.frame_slot(timestamp=bad)
    # set inside the block: checked when it ends, and the slot given back
    with (
        pytest.raises(ValueError, match="timestamp must be None or a finite number"),
        engine.frame_slot() as slot,
    ):
        slot.array[:] = frame(0)
        slot.timestamp = bad
    assert input_slots_free(engine) == slots
    fid = engine.submit(frame(4), timestamp=np.float32(12.5))
    assert engine.wait(fid, timeout=10)["depth"].capture_time == 12.5


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "1", None, True])
def test_wait_and_results_refuse_a_timeout_that_is_not_a_finite_number_of_seconds(engine, bad):
    fid = engine.submit(frame(5))
    t = time.monotonic()
    with pytest.raises(ValueError, match="timeout must be a finite number of seconds"):
        engine.wait(fid, timeout=bad)
    with pytest.raises(ValueError, match="timeout must be a finite number of seconds"):
        engine.results(timeout=bad)
    assert time.monotonic() - t < 3  # refused before any wait
    assert set(engine.wait(fid, timeout=np.float64(10))) == {"depth", "seg", "det"}


def test_a_negative_timeout_is_a_deadline_already_past_and_waits_for_nothing(engine):
    fid = engine.submit(frame(6))
    assert set(engine.wait(fid, timeout=10)) == {"depth", "seg", "det"}
    t = time.monotonic()
    assert set(engine.wait(fid, timeout=-0.5)) == {"depth", "seg", "det"}  # already there: no wait needed
    engine.results(timeout=-3.0)
    assert time.monotonic() - t < 3.0  # a wait of the 10 s timeout's kind would show


def test_set_rate_refuses_bools_and_takes_numpy_numbers(engine):
    for bad in (True, False, np.bool_(True), "5", math.nan, -1):
        with pytest.raises(
            ValueError, match=r"rate for 'seg' must be None \(no limit\) or a number of Hz from 0 to 10000"
        ):
            engine.set_rate("seg", bad)
    engine.set_rate("seg", np.float32(7.5))
    assert engine.rate("seg") == 7.5
    engine.set_rate("seg", np.int64(3))
    assert engine.rate("seg") == 3.0
    engine.set_rate("seg", None)


def test_a_tensor_that_requires_grad_is_a_value_error(engine):
    t = torch.from_numpy(frame(6).astype(np.float32)).requires_grad_(True)
    with pytest.raises(ValueError, match="requires grad"):
        engine.submit(t)
    fid = engine.submit(torch.from_numpy(frame(6)))
    assert set(engine.wait(fid, timeout=10)) == {"depth", "seg", "det"}


@pytest.mark.parametrize("bad", ["abc", 0.5, True, np.float64(1.0)], ids=repr)
def test_wait_checks_its_frame_id_as_submit_does(engine, bad):
    with pytest.raises(ValueError, match="frame_id must be an integer, got ") as e:
        engine.wait(bad)
    assert repr(bad) in str(e.value)


def test_wait_for_a_cancelled_frame_slots_id_says_so(engine):
    with engine.frame_slot() as slot:
        slot.cancel()
    with pytest.raises(ValueError, match="frame_id is None: no frame was submitted"):
        engine.wait(slot.frame_id)


def test_one_head_name_is_a_list_of_one_and_a_bad_one_says_what_is_taken(engine):
    fid = engine.submit(frame(0))
    assert set(engine.wait(fid, heads="depth")) == {"depth"}  # not the characters of 'depth'
    with pytest.raises(ValueError, match=r"^heads=\[\] names nothing; leave it out \(None\) for all$"):
        engine.wait(fid, heads=[])
    with pytest.raises(ValueError, match=r"^heads must be names \(str\), one or several, got \['depth', 3\]$"):
        engine.wait(fid, heads=["depth", 3])
    assert set(engine.wait(fid, heads={"depth", "seg"})) == {"depth", "seg"}  # any collection of names
    with pytest.raises(ValueError, match=r"a head is named by a str, got \['depth'\]"):
        engine.latest(["depth"])
    assert all(r.head == "seg" for r in engine.results(0.0, heads="seg"))


def test_one_override_is_a_list_of_one():
    from vpengine.config import load_config

    assert load_config("tiny", "mode=process").mode == "process"
