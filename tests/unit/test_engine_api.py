"""The Engine API in thread mode (one process): input checks, results, waits, rates, stats, lifecycle."""

from __future__ import annotations

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


BAD_FRAMES = [
    (np.zeros((120, 160), np.uint8), r"got shape \(120, 160\) \(a single-channel image: convert it, e.g. cv2"),
    (np.zeros((120, 160, 1), np.uint8), r"got shape \(120, 160, 1\) \(a single-channel image: convert it"),
    (np.zeros((2, 120, 160, 3), np.uint8), r"got shape \(2, 120, 160, 3\) \(4 dimensions\)"),
    (np.zeros((120, 160, 4), np.uint8), r"got shape \(120, 160, 4\) \(4 channels\)"),
    (np.zeros((9000, 14, 3), np.uint8), r"got 14x9000 \(raise input.max_frame_side to allow it\)"),
    (np.zeros((120, 160, 3), np.float32), r"got dtype float32"),
    (np.zeros((0, 160, 3), np.uint8), r"got an empty array"),
    ([[1, 2, 3]], r"got list"),
]


@pytest.mark.parametrize(("bad", "why"), BAD_FRAMES, ids=[b[1][:24] for b in BAD_FRAMES])
def test_bad_frames_raise_value_error_naming_expectation_and_engine_keeps_running(engine, bad, why):
    with pytest.raises(
        ValueError,
        match=r"expected an HxWx3 uint8 numpy array \(BGR\) of any size up to 8192 px a side \(the models run at "
        r"160x120\); " + why,
    ):
        engine.submit(bad)
    fid = engine.submit(frame(1))
    assert set(engine.wait(fid, timeout=5)) == {"depth", "seg", "det"}


def test_nan_in_a_float_frame_is_rejected():
    with Engine(tiny("thread", "input.dtype=float32")) as e:
        f = np.random.default_rng(0).random((120, 160, 3), dtype=np.float32)
        f[3, 4, 1] = np.nan
        with pytest.raises(ValueError, match="with finite values; got NaN or inf"):
            e.submit(f)
        f[3, 4, 1] = 0.5
        fid = e.submit(f)
        assert e.wait(fid, timeout=5)["depth"].frame_id == fid
        assert e.stats()["engine"]["rejected"] == 1


def test_wait_returns_each_head_with_frame_id_capture_time_and_latency(engine):
    fid = engine.submit(frame(2), frame_id=1234, timestamp=1700000000.25)
    out = engine.wait(fid, timeout=5)
    assert set(out) == {"depth", "seg", "det"}
    for head, r in out.items():
        assert r.head == head and r.frame_id == 1234 and r.capture_time == 1700000000.25
        assert 0 < r.latency < 5
    assert out["depth"]["depth"].shape == (120, 160) and out["depth"]["depth"].dtype == np.float32
    assert out["seg"]["classes"].dtype == np.uint8
    det = out["det"].outputs
    assert len(det["boxes"]) == det["count"] <= 16  # trimmed to the count, never above capacity
    assert engine.submit(frame(3)) == 1235  # automatic ids continue after a given one


def test_latest_returns_the_newest_output(engine):
    for i in range(3):
        fid = engine.submit(frame(10 + i))
        engine.wait(fid, timeout=5)
    r = engine.latest("depth")
    assert r is not None and r.frame_id == fid
    with pytest.raises(KeyError, match="no head named 'nope'"):
        engine.latest("nope")


def test_results_stream_in_order_and_counts_what_was_not_collected():
    with Engine(tiny("thread")) as e:
        assert e.results() == []  # starts the stream
        ids = [e.submit(frame(i)) for i in range(1)]
        e.wait(ids[-1], timeout=5)
        res = e.results(timeout=1)
        assert sorted((r.head, r.frame_id) for r in res) == [("depth", 0), ("det", 0), ("seg", 0)]
        for i in range(20):  # nobody calls results(): only the last output.slots + the leases (4 + 2) survive
            e.wait(e.submit(frame(i)), timeout=5)
        res = e.results(timeout=1)
        per_head = {h: [r.frame_id for r in res if r.head == h] for h in ("depth", "seg", "det")}
        assert all(v == [15, 16, 17, 18, 19, 20] for v in per_head.values()), per_head
        st = e.stats()["results"]["depth"]
        assert (st["delivered"], st["missed"], st["pending"]) == (7, 14, 0)


def test_set_rate_validates_and_stats_and_rate_show_it(engine):
    engine.set_rate("seg", 12.5)
    assert engine.stats()["models"]["seg"]["target_hz"] == 12.5 == engine.rate("seg")
    engine.set_rate("seg", 0)
    assert engine.rate("seg") == 0.0 and engine.rate("depth") is None
    engine.set_rate("seg", None)
    assert engine.stats()["models"]["seg"]["target_hz"] is None and engine.rate("seg") is None
    for call in (lambda: engine.set_rate("segm", 5), lambda: engine.rate("segm")):
        with pytest.raises(KeyError, match=r"no model named 'segm'; models: \['foundation', 'depth', 'seg', 'det'\]"):
            call()
    for bad in (-1, float("nan"), float("inf"), "fast", 10_000.5):
        with pytest.raises(ValueError, match=r"must be None \(no limit\) or a number of Hz from 0 to 10000"):
            engine.set_rate("seg", bad)


def test_stats_report_counters_and_memory(engine):
    fid = engine.submit(frame(5))
    engine.wait(fid, timeout=5)
    st = engine.stats()
    assert st["engine"]["mode"] == "thread" and st["engine"]["submitted"] >= 1
    for name in ("foundation", "depth", "seg", "det"):
        m = st["models"][name]
        assert m["state"] == "running" and m["runs"] >= 1 and m["errors"] == 0
        assert m["runs"] + m["skipped"] + m["dropped"] == m["frames_seen"]
        assert m["latency_ms"]["p50"] > 0
    mem = st["memory"]
    boxes = mem["mailboxes"]
    assert set(boxes) == {"input", "features", "out.depth", "out.seg", "out.det"}
    for where, key in (("host", "mailbox_host_bytes"), ("device", "mailbox_device_bytes")):
        at = [v["bytes"] for v in boxes.values() if (v["location"] == "cpu") == (where == "host")]
        assert mem[key] == sum(at), (where, boxes)
    # the input stays on the host; the output mailboxes keep output.slots + 2 lease slots each
    assert boxes["input"]["location"] == "cpu"
    assert all(boxes[f"out.{h}"]["slots"] == 4 + 2 for h in ("depth", "seg", "det"))


def test_recent_runs_are_each_lanes_runs_in_order_with_their_latencies():
    with Engine(tiny("thread", "cameras=[{name: front}, {name: rear}]")) as e:
        t0 = time.monotonic()
        for i in range(4):
            for cam in ("front", "rear"):
                assert "depth" in e.wait(e.submit(frame(i), camera=cam), timeout=10)
        starts, e2e = e.recent_runs("depth", since=t0)
        assert len(starts) == len(e2e) == 8 and np.all(np.diff(starts) >= 0) and starts[0] >= t0
        assert np.all((e2e > 0) & (e2e < 10))
        front = e.recent_runs("depth", camera="front", since=t0)
        rear = e.recent_runs("depth", camera="rear", since=t0)
        assert len(front[0]) == len(rear[0]) == 4  # each camera's lane, and every run keeps its own latency:
        assert set(zip(*front)) | set(zip(*rear)) == set(zip(starts, e2e))
        assert len(e.recent_runs("depth", since=time.monotonic() + 1)[0]) == 0
        assert len(e.recent_runs("foundation", since=t0)[0]) == 8  # a run of each camera's lane
        with pytest.raises(KeyError):
            e.recent_runs("nope")
        with pytest.raises(ValueError, match="serves cameras"):
            e.recent_runs("depth", camera="side")


def test_wait_on_unknown_frame_and_timeout():
    slow = ["heads.seg.model=helpers.faulty:FaultyHead", "heads.seg.options={sleep_ms: 2000}"]
    with Engine(tiny("thread", *slow)) as e:
        with pytest.raises(ValueError, match="frame id 99 was not submitted"):
            e.wait(99)
        fid = e.submit(frame(1))
        with pytest.raises(TimeoutError, match=r"no output from \['seg'\] within 0.3 s"):
            e.wait(fid, timeout=0.3)
        assert set(e.wait(fid, heads=["depth", "det"], timeout=5)) == {"depth", "det"}


def test_a_paused_or_rate_limited_head_answers_at_once_with_no_output():
    # Note [Answered frames]: wait ends as soon as a head knows it gives no output for the frame
    with Engine(tiny("thread", "heads.seg.rate_hz=0", "heads.det.rate_hz=1")) as e:
        t0 = 1000.0
        first = e.wait(e.submit(frame(1), timestamp=t0), timeout=5)
        assert set(first) == {"depth", "det"}  # seg paused
        for i in range(1, 5):  # frames 0.1 s apart on their own clock: det (1 Hz) holds them back
            t = time.monotonic()
            out = e.wait(e.submit(frame(1 + i), timestamp=t0 + 0.1 * i), timeout=5)
            assert set(out) == {"depth"} and time.monotonic() - t < 3.0  # not the 5 s timeout
        assert set(e.wait(e.submit(frame(9), timestamp=t0 + 1.0), timeout=5)) == {"depth", "det"}
        e.set_rate("foundation", 0)
        t = time.monotonic()
        assert e.wait(e.submit(frame(10), timestamp=t0 + 2.0), timeout=5) == {}
        assert time.monotonic() - t < 1.0


def test_lifecycle_stop_is_idempotent_and_a_stopped_engine_says_so():
    e = Engine(tiny("thread"))
    with pytest.raises(EngineDeadError, match="call start"):
        e.submit(frame(0))
    e.start()
    with pytest.raises(RuntimeError, match="starts once"):
        e.start()
    e.stop()
    e.stop()
    with pytest.raises(EngineDeadError, match="stopped"):
        e.submit(frame(0))
    with pytest.raises(EngineDeadError, match="stopped"):
        e.rate("depth")
    assert e.stats() == {"engine": {"state": "stopped"}}


def test_fp16_models_on_a_cpu_are_warned_about(caplog):
    """PyTorch runs fp16 slowly on a CPU (the shipped GPU config run with --device cpu took seconds a frame)."""
    import logging

    with caplog.at_level(logging.WARNING, "vpengine"):
        Engine(tiny("thread", "precision=fp16", "heads.seg.precision=fp32"))  # planned only
    said = [m for m in caplog.messages if "fp16 on the CPU" in m]
    assert said == [
        "foundation, depth, det run in fp16 on the CPU, which PyTorch does slowly (float32 is the CPU's); "
        "precision: fp32 (or --set precision=fp32) for a CPU run"
    ]
    caplog.clear()
    with caplog.at_level(logging.WARNING, "vpengine"):
        Engine(tiny("thread"))
    assert not [m for m in caplog.messages if "fp16" in m]


def test_a_postprocess_block_a_model_never_reads_is_said_to_be_ignored(caplog):
    """A typo'd or misplaced postprocess block ran without a word; said once, while planning."""
    import logging

    with caplog.at_level(logging.WARNING, "vpengine"):
        Engine(tiny("thread", "heads.seg.postprocess.outptu=both"))
    said = [m for m in caplog.messages if "postprocess" in m]
    assert said == [
        "seg: postprocess ['outptu'] is set, but model 'tiny_seg' reads no postprocess options (of the zoo's, the "
        "depth heads do): it is ignored"
    ]


def test_a_config_that_starts_with_nothing_coming_out_says_so(caplog):
    import logging

    with caplog.at_level(logging.WARNING, "vpengine"):
        Engine(tiny("thread", "heads=[]", "foundation_model.rate_hz=0"))
    assert [m for m in caplog.messages if "no heads" in m or "starts paused" in m] == [
        "the config has no heads: the foundation model runs on each frame and no result comes out",
        "foundation_model.rate_hz is 0: the engine starts paused, and no frame runs until set_rate('foundation', "
        "...) raises it",
    ]


def test_process_groups_in_thread_mode_are_said_to_mean_nothing(caplog):
    import logging

    with caplog.at_level(logging.WARNING, "vpengine"):
        Engine(tiny("thread", "heads.depth.process=heads", "heads.seg.process=heads"))
    assert "depth, seg: process is for process mode; in thread mode every model shares this process already" in (
        caplog.messages
    )
