"""Several cameras on one engine (Note [Cameras] in runtime/worker.py), thread mode on the CPU: frames tagged with
their camera, outputs in each camera's own grid, a head limited to one camera, rates and counters per camera."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest

from helpers.frames import frame
from helpers.waiting import wait_for
from tests_paths import tiny
from vpengine.engine import Engine
from vpengine.pipeline.pacing import pipelined

CAMERAS = ["cameras=[{name: front}, {name: rear, height: 90, width: 200}]", "heads.seg.cameras=[rear]"]
# one worker runs them all: the module's engines start once a mode
pytestmark = pytest.mark.xdist_group("cameras")


@pytest.fixture(scope="module", params=["thread", "process"])
def engine(request):
    with Engine(tiny(request.param, *CAMERAS)) as e:
        yield e


def test_each_frame_comes_back_tagged_with_its_camera_in_its_own_grid(engine):
    assert engine.cameras == ["front", "rear"]
    f = engine.submit(frame(1, 240, 320), camera="front")
    r = engine.submit(frame(2, 90, 200), camera="rear")
    front, rear = engine.wait(f, timeout=30), engine.wait(r, timeout=30)
    assert set(front) == {"depth", "det"}  # seg serves the rear camera only
    assert set(rear) == {"depth", "seg", "det"}
    assert {x.camera for x in front.values()} == {"front"} and {x.camera for x in rear.values()} == {"rear"}
    assert front["depth"]["depth"].shape == (240, 320) and rear["depth"]["depth"].shape == (90, 200)
    assert rear["seg"]["classes"].shape == (90, 200)
    assert (rear["det"]["boxes"][:, [0, 2]] <= 200).all() and (rear["det"]["boxes"][:, [1, 3]] <= 90).all()


def test_the_same_picture_gives_the_same_outputs_from_either_camera(engine):
    img = frame(7)
    a = engine.wait(engine.submit(img, camera="front"), timeout=30)
    b = engine.wait(engine.submit(img, camera="rear"), timeout=30)
    np.testing.assert_allclose(a["depth"]["depth"], b["depth"]["depth"], rtol=1e-5, atol=1e-6)


def test_latest_of_a_camera_is_its_own_newest_not_the_newest_of_any_cameras(engine):
    f = engine.wait(engine.submit(frame(1, 240, 320), camera="front"), timeout=30)["depth"]
    r = engine.wait(engine.submit(frame(2, 90, 200), camera="rear"), timeout=30)["depth"]
    assert engine.latest("depth").frame_id == r.frame_id  # of any camera's: the rear frame came last
    front, rear = engine.latest("depth", camera="front"), engine.latest("depth", camera="rear")
    assert (front.frame_id, front.camera, front["depth"].shape) == (f.frame_id, "front", (240, 320))
    assert (rear.frame_id, rear.camera) == (r.frame_id, "rear")
    with pytest.raises(ValueError, match=r"'seg' serves cameras \['rear'\], not 'front'"):
        engine.latest("seg", camera="front")
    with pytest.raises(ValueError, match=r"no camera named 'side'; cameras: \['front', 'rear'\]"):
        engine.latest("depth", camera="side")


def test_the_memory_report_names_each_model_once_not_its_lanes(engine):
    mem = engine.stats()["memory"]
    assert set(mem["models_device_bytes"]) == {"foundation", "depth", "seg", "det"}  # no per-camera entries
    assert all(v == 0 for v in mem["models_device_bytes"].values())  # on the CPU: no device memory


def test_a_camera_must_be_named_and_known():
    with Engine(tiny("thread", *CAMERAS)) as e:
        with pytest.raises(ValueError, match=r"this engine has cameras \['front', 'rear'\]: say which one"):
            e.submit(frame(0))
        with pytest.raises(ValueError, match=r"no camera named 'side'; cameras: \['front', 'rear'\]"):
            e.submit(frame(0), camera="side")
        with pytest.raises(ValueError, match=r"'seg' serves cameras \['rear'\], not 'front'"):
            e.set_rate("seg", 1, camera="front")


def test_rates_and_counters_are_per_camera():
    with Engine(tiny("thread", *CAMERAS)) as e:
        e.set_rate("depth", 0, camera="front")  # paused on one camera only
        assert e.rate("depth", "front") == 0 and e.rate("depth", "rear") is None
        for i in range(6):
            fa = e.submit(frame(i, 240, 320), camera="front")
            fb = e.submit(frame(i, 90, 200), camera="rear")
            assert "depth" not in e.wait(fa, timeout=30)
            assert "depth" in e.wait(fb, timeout=30)
        st = e.stats()
        cams = st["cameras"]
        assert cams["front"]["depth"]["runs"] == 0 and cams["rear"]["depth"]["runs"] == 6
        assert cams["front"]["depth"]["target_hz"] == 0 and cams["rear"]["depth"]["target_hz"] is None
        assert "seg" not in cams["front"] and cams["rear"]["seg"]["runs"] == 6
        assert cams["front"]["foundation"]["runs"] == 6 and cams["rear"]["foundation"]["runs"] == 6
        assert st["models"]["foundation"]["runs"] == 12 and st["models"]["depth"]["runs"] == 6
        assert st["models"]["depth"]["target_hz"] is None  # the rates differ: stats()["cameras"] says each


def test_frame_slot_lends_the_cameras_own_size():
    with Engine(tiny("thread", *CAMERAS)) as e:
        with e.frame_slot(camera="rear") as slot:
            assert slot.array.shape == (90, 200, 3)
            slot.array[...] = frame(3, 90, 200)
        out = e.wait(slot.frame_id, timeout=30)
        assert out["seg"].camera == "rear" and out["seg"]["classes"].shape == (90, 200)


def test_a_camera_fills_its_slot_while_another_cameras_slot_is_open():
    # Note [Frames of several cameras at once]: a slot is filled under its camera's lock, not the submit lock
    with Engine(tiny("thread", *CAMERAS)) as e:
        done = {c: threading.Event() for c in ("front", "rear")}
        ids: dict[str, int] = {}

        def submit(camera: str) -> None:
            ids[camera] = e.submit(frame(9), camera=camera)
            done[camera].set()

        with e.frame_slot(camera="rear") as slot:
            others = [threading.Thread(target=submit, args=(c,)) for c in ("front", "rear")]
            for t in others:
                t.start()
            assert done["front"].wait(10), "another camera's submit waited for an open slot"
            time.sleep(0.2)
            assert not done["rear"].is_set(), "the same camera's submit went through while its slot was open"
            slot.array[...] = frame(3, 90, 200)
            buffer = slot.array
        for t in others:
            t.join(10)
        assert ids["front"] < slot.frame_id < ids["rear"]  # ids in the order the frames were published
        assert e.wait(ids["rear"], timeout=30)["seg"].camera == "rear"  # the camera's newest: nothing skips it
        assert buffer is not None
        # frames of another size are fitted from a buffer of the camera's own: two cameras' blocks open at once,
        # each writing a frame of the same size, submit their own frames
        written, front_ids = threading.Event(), []

        def front_block() -> None:
            with e.frame_slot(camera="front", size=(90, 200)) as front:
                front.array[...] = frame(1, 90, 200)
                written.set()
                time.sleep(0.3)  # the rear camera's block opens, writes and closes meanwhile
            front_ids.append(front.frame_id)

        t = threading.Thread(target=front_block)
        t.start()
        assert written.wait(10)
        with e.frame_slot(camera="rear") as rear:
            rear.array[...] = frame(2, 90, 200)
        t.join(10)
        got = e.wait(front_ids[0], timeout=30)["depth"]["depth"]
        alone = e.wait(e.submit(frame(1, 90, 200), camera="front"), timeout=30)["depth"]["depth"]
        np.testing.assert_array_equal(got, alone)


def test_cameras_submitting_from_threads_of_their_own_get_every_frame_back_under_their_own_ids():
    cams = [f"c{i}" for i in range(4)]
    with Engine(tiny("thread", "cameras=[" + ", ".join(f"{{name: {c}}}" for c in cams) + "]")) as e:
        ids: dict[str, list[int]] = {c: [] for c in cams}
        answered: dict[str, list[str]] = {c: [] for c in cams}
        go = threading.Barrier(len(cams))

        def drive(camera: str) -> None:  # a camera's driver: its next frame once the last one is answered
            go.wait()
            for i in range(30):
                ids[camera].append(e.submit(frame(i), camera=camera))
                answered[camera] += [r.camera for r in e.wait(ids[camera][-1], heads=["depth"], timeout=30).values()]

        threads = [threading.Thread(target=drive, args=(c,)) for c in cams]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        every = [f for c in cams for f in ids[c]]
        assert len(every) == 4 * 30 and len(set(every)) == len(every)
        for c in cams:
            assert ids[c] == sorted(ids[c])  # a camera's frames in the order it handed them in
            assert answered[c] == [c] * 30
        assert e.stats()["engine"]["submitted"] == 4 * 30


def test_one_camera_engines_keep_their_names_and_layout():
    with Engine(tiny("thread")) as e:
        assert e.cameras == ["camera"]
        out = e.predict(frame(1))
        assert {r.camera for r in out.values()} == {"camera"}
        assert e.stats()["cameras"] == {}


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_frames_that_come_together_run_as_one_batch_and_give_what_they_give_alone(mode):
    with Engine(tiny(mode, "cameras=[{name: front}, {name: rear}]", "runtime.batch_window_ms=100")) as e:
        alone = [e.wait(e.submit(frame(i), camera="front"), timeout=30) for i in range(3)]
        assert e.stats()["models"]["foundation"]["batched"] == 0  # one camera's frames: nothing to batch with
        for _ in range(8):
            for i in range(3):  # each picture from both cameras at once, the two frames' contents differing
                ids = [e.submit(frame(i), camera="front"), e.submit(frame(i + 5), camera="rear")]
                front, rear = (e.wait(f, timeout=30) for f in ids)
                for head, key in (("depth", "depth"), ("seg", "classes"), ("det", "boxes")):
                    np.testing.assert_allclose(front[head][key], alone[i][head][key], rtol=1e-4, atol=1e-5)
                assert front["depth"].camera == "front" and rear["depth"].camera == "rear"
        models = e.stats()["models"]
        # after each camera's frame spacing is known, the backbone waits for the other camera's frame: one call. A
        # pair not run together was split for a reason the model counts (Note [Cameras]: a frame deferred while the
        # model seemed behind, a guess a loaded machine can mislead, or one that came too late): two frames each
        for m in ("foundation", "depth"):
            st = models[m]
            assert st["batched"] + 2 * (st["deferred"] + st["late"]) >= 24 and st["batched"] > 0, st
        assert models["foundation"]["runs"] == 51 and models["foundation"]["dropped"] == 0
        # a model call a batch: two frames in each pair that ran together. A call's batch counts are added after its
        # outputs are published, so the last call's may still be on their way when the wait above returns
        for m in ("foundation", "depth"):

            def counted(m: str = m) -> bool:
                st = e.stats()["models"][m]
                return st["batches"] == st["runs"] - st["batched"] // 2

            wait_for(counted, timeout=10, what=f"{m}'s batch counts", show=lambda m=m: e.stats()["models"][m])


def test_after_a_pause_a_ticks_frames_run_as_one_batch_again_within_three_ticks():
    """Note [Cameras]: a batch waits for the cameras whose next frame is due, read off each camera's recent frame
    spacing. One long gap (a stream paused, a warm-up of frames one at a time) must not make the engine think the
    cameras slow: a moving average of the spacing did for a dozen ticks, and each tick's frames ran in two or three
    batches."""
    cams = [f"c{i}" for i in range(4)]
    names = ", ".join(f"{{name: {c}}}" for c in cams)
    with Engine(tiny("thread", f"cameras=[{names}]", "runtime.batch_window_ms=50")) as e:

        def ticks(n: int) -> None:
            """``n`` ticks at 10 Hz, a frame of every camera each, handed in one after another by one thread; then
            every frame answered (run, or skipped if the model fell behind)."""
            ids = []
            for _ in range(n):
                t = time.monotonic()
                ids += [e.submit(frame(1), camera=c) for c in cams]
                time.sleep(max(0.0, t + 0.1 - time.monotonic()))
            for f in ids:
                e.wait(f, timeout=30)

        def counts() -> tuple[int, int, int]:
            st = e.stats()["models"]["foundation"]
            return st["runs"], st["skipped"], st["batches"]

        ticks(5)
        time.sleep(2.0)
        ticks(2)  # the first tick after it waits for no camera (none is live); the second learns
        before = counts()
        ticks(10)
        runs, skipped, batches = (a - b for a, b in zip(counts(), before))
        assert runs + skipped == 40, (runs, skipped)
        # one batch a tick; a few split by a loaded machine's stalls (the moving average: 17 for these 10 ticks)
        assert batches <= 13, f"{batches} batches for 10 ticks"


@pytest.mark.parametrize(("window_ms", "hz"), [(100, 30), (5, 30), (5, None), (20, None)])
def test_a_batch_window_as_long_as_a_cameras_frame_spacing_is_said_once(window_ms, hz, caplog):
    """Note [Cameras]: with a window of a frame period or more a batch may wait for a camera's next frame; the
    engine says so once. The default window says nothing, and no window says anything of frames handed in as fast
    as they go (a file run: hz None), closer than the window but no camera's spacing."""
    cfg = tiny("thread", "cameras=[{name: front}, {name: rear}]", f"runtime.batch_window_ms={window_ms}")
    if hz is None:  # as `vpengine run` of files: every frame, in order (Note [Frames in flight])
        cfg = pipelined(cfg)[0]
    with caplog.at_level(logging.WARNING, logger="vpengine.worker"), Engine(cfg) as e:
        ids = []
        for _ in range(10):  # both cameras at once
            t = time.monotonic()
            ids += [e.submit(frame(1), camera="front"), e.submit(frame(2), camera="rear")]
            if hz is not None:
                time.sleep(max(0.0, t + 1 / hz - time.monotonic()))
        for f in ids:
            e.wait(f, timeout=30)
    said = [r.getMessage() for r in caplog.records if "batch_window_ms" in r.getMessage()]
    if window_ms == 5 or hz is None:
        assert said == []
    else:
        assert len(said) == 1 and said[0].startswith("runtime.batch_window_ms is 100 ms, as long as camera "), said


def test_a_batch_that_fails_answers_every_camera_and_the_head_goes_on(tmp_path, restart_backoff):
    restart_backoff(0.2)
    cfg = tiny(
        "thread",
        "cameras=[{name: front}, {name: rear}]",
        "runtime.batch_window_ms=100",
        "heads.seg.model=helpers.faulty:FaultyHead",
        f'heads.seg.options={{"raise_at_run": 4, "once_marker": "{tmp_path / "raised"}"}}',
    )
    with Engine(cfg) as e:
        missing = []
        for i in range(12):
            ids = [e.submit(frame(i), camera="front"), e.submit(frame(i + 3), camera="rear")]
            for f in ids:
                t0 = time.monotonic()
                out = e.wait(f, timeout=30)
                assert time.monotonic() - t0 < 5  # answered, never waited out
                assert {"depth", "det"} <= set(out)
                if "seg" not in out:
                    missing.append(f)
        seg = e.stats()["models"]["seg"]
        assert seg["errors"] == 1 and "injected failure at run 4" in seg["last_error"]
        assert seg["restarts"] == 0  # a batch that raised fails its frames, not the worker (Note [Frame errors])
        assert 1 <= len(missing) <= 6, missing  # the failed batch's frames (and any while it restarted)
        for i in range(20):  # serving both cameras again, every frame
            ids = [e.submit(frame(i), camera="front"), e.submit(frame(i + 3), camera="rear")]
            assert all("seg" in e.wait(f, timeout=30) for f in ids)
        st = e.stats()["cameras"]
        assert st["front"]["seg"]["runs"] + st["rear"]["seg"]["runs"] >= 40 + 24 - len(missing)


@pytest.mark.parametrize("mailbox", ["features", "input"])
def test_a_mailbox_has_room_for_a_slot_a_camera_in_writing_while_every_reader_pins_another_frame(mailbox):
    """The foundation acquires one feature slot per camera of its batch before it publishes any (Note [Tagged
    slots]), and the cameras' threads fill an input slot each at once (Note [Frames of several cameras at once] in
    engine/core.py): with every reader pinning a slot of its own and each camera's newest kept, all of them must
    still be free. A mailbox sized for one slot in writing crashed the foundation with two cameras and slow heads."""
    from vpengine.runtime.plan import mailboxes, make_plan
    from vpengine.transport import SlotRing

    cfg = tiny("thread", "cameras=[{name: front}, {name: rear}, {name: left}]")
    box = next(m for m in mailboxes(make_plan(cfg), shared=False) if m["name"] == mailbox)
    ring = SlotRing.create(**box)
    try:
        writer, tags = ring.writer(), len(cfg.camera_names())
        readers = [ring.reader(r.name) for r in box["readers"]]
        pinned = []
        for round_ in range(len(readers) // tags + 1):  # each round: a frame per camera, one new reader per camera
            for tag in range(tags):
                slot = writer.acquire(timeout=0)
                assert slot is not None
                writer.publish(slot, round_ * tags + tag, 0.0, 0.0, tag=tag)
            for reader in readers[round_ * tags : (round_ + 1) * tags]:
                pinned.append((reader, reader.pin(timeout=0)))
        assert all(slot is not None for _, slot in pinned)
        assert len({slot.index for _, slot in pinned}) == len(readers)  # every reader holds a frame of its own
        batch = [writer.acquire(timeout=0) for _ in range(tags)]  # the next batch, all taken before any publish
        assert all(slot is not None for slot in batch)
    finally:
        ring.close()
