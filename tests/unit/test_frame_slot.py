"""Engine.frame_slot: a frame written in place into the input mailbox (Note [Frame slots]), thread mode."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine, EngineDeadError


@pytest.fixture(scope="module")
def engine():
    with Engine(tiny("thread")) as e:
        yield e


def _outputs(res):
    return {h: {k: np.array(v) for k, v in r.outputs.items()} for h, r in res.items()}


def test_a_frame_written_into_the_slot_gives_what_submit_gives(engine):
    img = frame(7)
    want = _outputs(engine.wait(engine.submit(img), timeout=5))
    with engine.frame_slot(timestamp=1700000000.5) as slot:
        assert slot.array.shape == (120, 160, 3) and slot.array.dtype == np.uint8 and slot.array.flags.writeable
        slot.array[...] = img
    assert slot.array is None  # the slot is the engine's again
    out = engine.wait(slot.frame_id, timeout=5)
    assert out["depth"].capture_time == 1700000000.5
    got = _outputs(out)
    for head in want:
        for key in want[head]:
            np.testing.assert_array_equal(got[head][key], want[head][key], err_msg=f"{head}.{key}")


def test_frame_ids_continue_across_submit_and_frame_slot_and_a_given_id_is_kept(engine):
    a = engine.submit(frame(1))
    with engine.frame_slot() as s:
        s.array[...] = frame(2)
    assert s.frame_id == a + 1
    with engine.frame_slot(frame_id=5000) as s:
        s.array[...] = frame(3)
        s.timestamp = 12.5  # a capture stamp known only after the read
    assert s.frame_id == 5000
    r = engine.wait(5000, timeout=5)["seg"]
    assert r.frame_id == 5000 and r.capture_time == 12.5
    assert engine.submit(frame(4)) == 5001


def test_cancel_and_an_exception_submit_nothing_and_the_engine_goes_on(engine):
    before = engine.stats()["engine"]["submitted"]
    with engine.frame_slot() as s:
        s.array[...] = frame(5)
        s.cancel()
    assert s.frame_id is None
    with pytest.raises(OSError, match="camera unplugged"), engine.frame_slot() as s2:
        s2.array[:60] = 0
        raise OSError("camera unplugged")
    assert s2.frame_id is None
    assert engine.stats()["engine"]["submitted"] == before
    fid = engine.submit(frame(6))
    assert set(engine.wait(fid, timeout=5)) == {"depth", "seg", "det"}
    assert engine.stats()["engine"]["submitted"] == before + 1


def test_an_open_slot_is_never_read_and_other_writers_wait_for_it():
    every_frame = (
        "foundation_model.input_mode=fifo",
        "heads.depth.input_mode=fifo",
        "heads.depth.output.slots=8",
    )
    with Engine(tiny("thread", *every_frame)) as e:
        e.wait(e.submit(frame(0)), timeout=5)
        runs = e.stats()["models"]["foundation"]["runs"]
        done = threading.Event()
        other: list[int] = []

        def submit_from_another_thread() -> None:
            other.append(e.submit(frame(9)))
            done.set()

        with e.frame_slot() as s:
            s.array[:60] = 255  # half a frame
            t = threading.Thread(target=submit_from_another_thread)
            t.start()
            time.sleep(0.3)
            assert not done.is_set(), "a submit went through while a frame slot was open"
            assert e.stats()["models"]["foundation"]["runs"] == runs, "the foundation read an unfinished frame"
            with pytest.raises(RuntimeError, match="frame_slot is open in this thread"):
                e.submit(frame(1))
            with pytest.raises(RuntimeError, match="frame_slot is open in this thread"):
                e.frame_slot()
            s.array[60:] = 255
        t.join(5)
        assert done.is_set() and other == [s.frame_id + 1]  # in order: the slot's frame first
        full = e.wait(s.frame_id, timeout=5)["depth"]["depth"]
        ref = e.wait(e.submit(np.full((120, 160, 3), 255, np.uint8)), timeout=5)["depth"]["depth"]
        np.testing.assert_array_equal(full, ref)


def test_a_slot_is_used_once_and_a_stopped_engine_lends_none():
    e = Engine(tiny("thread"))
    with pytest.raises(EngineDeadError, match="call start"):
        e.frame_slot()
    with e:
        s = e.frame_slot()
        with s:
            s.array[...] = frame(1)
        with pytest.raises(RuntimeError, match="one with-block"):
            s.__enter__()
        late = e.frame_slot()
    with pytest.raises(EngineDeadError, match="stopped"):
        late.__enter__()
    with pytest.raises(EngineDeadError, match="stopped"):
        e.frame_slot()


def test_process_mode_reads_the_slot_written_in_the_parent():
    with Engine(tiny("process")) as e:
        img = frame(11)
        want = _outputs(e.wait(e.submit(img), timeout=30))
        with e.frame_slot() as s:
            np.copyto(s.array, img)
        got = _outputs(e.wait(s.frame_id, timeout=30))
    for head in want:
        for key in want[head]:
            np.testing.assert_array_equal(got[head][key], want[head][key], err_msg=f"{head}.{key}")
