"""Note [Sink thread]: results written on a background thread, in order, with nothing lost unless counted, and a
sink's failure raised in the caller."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from vpengine.engine.results import Result
from vpengine.io.sinks import Sink, SinkThread


def result(head: str, i: int) -> Result:
    return Result(head, i, float(i), 0.001, {"x": np.full(3, i)})


class Recorder(Sink):
    def __init__(self, delay_s: float = 0.0, fail_at: int | None = None, fail_close: bool = False) -> None:
        self.delay_s, self.fail_at, self.fail_close = delay_s, fail_at, fail_close
        self.written: list[tuple[str, int, str]] = []
        self.threads = {threading.current_thread().name}  # made, written and closed on
        self.closed = False
        self.gate = threading.Event()  # cleared: the writer stalls in its first write
        self.gate.set()
        self.entered = threading.Event()

    def write(self, result: Result, frame: np.ndarray | None, name: str) -> None:
        self.entered.set()
        self.gate.wait()
        if result.frame_id == self.fail_at:
            raise OSError(28, "No space left on device")
        time.sleep(self.delay_s)
        self.threads.add(threading.current_thread().name)
        self.written.append((result.head, result.frame_id, name))

    def close(self) -> None:
        self.threads.add(threading.current_thread().name)
        self.closed = True
        if self.fail_close:
            raise OSError("bag index not written")


def maker(made: list[Recorder], **kw: object):  # type: ignore[no-untyped-def]
    """A factory that makes a Recorder (in whichever thread calls it) and keeps it in ``made``."""

    def make() -> Recorder:
        made.append(Recorder(**kw))  # type: ignore[arg-type]
        return made[-1]

    return make


def test_every_result_reaches_every_sink_in_order_off_the_callers_thread():
    made: list[Recorder] = []
    w = SinkThread([maker(made, delay_s=0.002), maker(made)], max_pending=4, block=True)
    a, b = made
    for i in range(30):
        for h in ("depth", "seg"):
            w.put(result(h, i), None, f"{i:06d}")
    w.close()
    want = [(h, i, f"{i:06d}") for i in range(30) for h in ("depth", "seg")]
    assert a.written == want and b.written == want and a.closed and b.closed
    assert a.threads == b.threads == {"vpengine-sinks"} and not w.unwritten  # as an SQLite bag needs


def test_a_full_queue_waits_when_blocking_and_counts_what_it_leaves_unwritten_when_not():
    sink = Recorder()
    sink.gate.clear()  # the writer stalls on the first result
    w = SinkThread([lambda: sink], max_pending=2, block=False)
    t0 = time.monotonic()
    w.put(result("seg", 0), None, "0")
    assert sink.entered.wait(5)
    for i in range(1, 10):
        w.put(result("depth" if i % 2 else "seg", i), None, str(i))
    # one result in the writer's hands, two queued, seven left unwritten and counted per head
    assert sum(w.unwritten.values()) == 7 and set(w.unwritten) == {"depth", "seg"}
    assert time.monotonic() - t0 < 4.0  # a live loop is never held up by the writer (stalled until the gate opens)
    sink.gate.set()
    w.close()
    assert len(sink.written) == 3 and [r[1] for r in sink.written] == [0, 1, 2]

    sink = Recorder()
    sink.gate.clear()
    w = SinkThread([lambda: sink], max_pending=2, block=True)
    w.put(result("depth", 0), None, "0")
    assert sink.entered.wait(5)
    for i in (1, 2):
        w.put(result("depth", i), None, str(i))
    t = threading.Thread(target=w.put, args=(result("depth", 3), None, "3"))
    t.start()
    t.join(0.3)
    assert t.is_alive()  # waits for room: nothing is dropped in lockstep
    sink.gate.set()
    t.join(5)
    w.close()
    assert [r[1] for r in sink.written] == [0, 1, 2, 3] and not w.unwritten


def test_a_sink_that_fails_is_raised_in_the_caller_once_and_nothing_hangs():
    sink = Recorder(fail_at=2)
    w = SinkThread([lambda: sink], max_pending=2, block=True)
    with pytest.raises(RuntimeError, match="writing outputs failed: .*No space left on device"):
        for i in range(1000):  # a blocking put on a queue a failed writer no longer writes must not wait forever
            w.put(result("depth", i), None, str(i))
    assert [r[1] for r in sink.written] == [0, 1]
    w.close()  # already raised: not again; the sink is still closed
    assert sink.closed

    sink = Recorder(fail_at=0)
    w = SinkThread([lambda: sink], max_pending=2, block=True)
    w.put(result("depth", 0), None, "0")
    with pytest.raises(RuntimeError, match="No space left"):
        w.close()  # the caller never put again: close reports it


def test_every_sink_is_closed_even_when_one_fails_to_close():
    bad, good = Recorder(fail_close=True), Recorder()
    w = SinkThread([lambda: bad, lambda: good], max_pending=1, block=True)
    w.put(result("seg", 0), None, "0")
    with pytest.raises(RuntimeError, match="closing outputs failed: .*bag index"):
        w.close()
    assert bad.closed and good.closed and good.written == [("seg", 0, "0")]
    w.close()  # twice is fine


def test_a_sink_that_cannot_be_made_raises_its_own_error_from_the_constructor_and_the_others_are_closed():
    made: list[Recorder] = []

    def bad() -> Sink:
        raise ValueError("output bag 'x' exists already; bags are never overwritten")

    with pytest.raises(ValueError, match="exists already"):
        SinkThread([maker(made), bad], max_pending=2, block=True)
    assert made[0].closed and made[0].threads == {"vpengine-sinks"}


def test_a_queue_of_no_results_is_refused():
    with pytest.raises(ValueError, match="max_pending must be >= 1, got 0"):
        SinkThread([], max_pending=0, block=True)


# ------------------------------------------------------------------------------------------------ files, pictures
def test_depth_as_16_bit_png_gives_the_depth_back_within_half_a_step_and_marks_what_was_not_finite():
    from vpengine.io.sinks import decode_depth_png, encode_depth_png

    rng = np.random.default_rng(1)
    d = (rng.random((48, 64)) * 30 + 0.5).astype(np.float32)
    d[3, 4], d[5, 6], d[7, 8] = np.nan, np.inf, -np.inf
    png, offset, scale = encode_depth_png(d)
    assert png.dtype == np.uint16 and png.min() == 0 and png.max() == 65535
    back = decode_depth_png(png, offset, scale)
    finite = np.isfinite(d)
    assert np.isnan(back[~finite]).all()
    step = (np.nanmax(d[finite]) - np.nanmin(d[finite])) / 65534
    assert np.abs(back[finite] - d[finite]).max() <= step / 2 + 1e-5 * np.abs(d[finite]).max()
    flat = np.full((4, 4), 2.5, np.float32)
    np.testing.assert_array_equal(decode_depth_png(*encode_depth_png(flat)), flat)
    assert np.isnan(decode_depth_png(*encode_depth_png(np.full((2, 2), np.nan, np.float32)))).all()


def head_results(i: int, n: int = 2) -> list[Result]:
    rng = np.random.default_rng(i)
    return [
        Result("depth", i, i / 10, 0.01, {"depth": (rng.random((60, 80)) * 5).astype(np.float32)}),
        Result("seg", i, i / 10, 0.01, {"classes": rng.integers(0, 3, (60, 80)).astype(np.uint8)}),
        Result(
            "det",
            i,
            i / 10,
            0.01,
            {
                "boxes": np.array([[1, 2, 30, 40], [5, 5, 9, 9], [0, 0, 0, 0]], np.float32),
                "scores": np.array([0.9, 0.6, 0], np.float32),
                "labels": np.array([1, 0, -1], np.int32),
                "count": np.array(n, np.int32),
            },
        ),
    ]


HEADS = {
    "depth": {"kind": "depth"},
    "seg": {"kind": "segmentation"},
    "det": {"kind": "detection", "labels": ["person", "car"]},
}


def test_the_folder_sink_writes_depth_as_png_with_its_scale_by_default_and_starts_line_files_afresh(tmp_path):
    import json

    from vpengine.io.sinks import FolderSink, load_depth

    frame = np.zeros((60, 80, 3), np.uint8)
    for _ in range(2):  # a second run into the same folder replaces the line files, never appends to them
        sink = FolderSink(tmp_path, HEADS, viz=True)
        for i in range(3):
            for r in head_results(i):
                sink.write(r, frame, f"f{i}")
        sink.close()
    assert sorted(p.name for p in (tmp_path / "depth").iterdir()) == [
        "depth_scale.jsonl", "f0.png", "f1.png", "f2.png", "viz",
    ]  # fmt: skip
    want = head_results(1)[0]["depth"]
    assert np.abs(load_depth(tmp_path / "depth", "f1") - want).max() < 5 / 65534
    lines = [json.loads(x) for x in (tmp_path / "det" / "detections.jsonl").read_text().splitlines()]
    assert [x["frame"] for x in lines] == ["f0", "f1", "f2"]
    assert lines[0]["names"] == ["car", "person"] and len(lines[0]["boxes"]) == 2  # the first `count` only
    assert len((tmp_path / "depth" / "depth_scale.jsonl").read_text().splitlines()) == 3
    assert sorted(p.name for p in (tmp_path / "seg" / "viz").iterdir()) == ["f0.jpg", "f1.jpg", "f2.jpg"]

    sink = FolderSink(tmp_path / "npy", HEADS, depth_format="npy")
    sink.write(head_results(1)[0], frame, "f1")
    sink.close()
    np.testing.assert_array_equal(load_depth(tmp_path / "npy" / "depth", "f1"), want)  # exact
    with pytest.raises(ValueError, match=r"depth_format must be one of \('png16', 'npy'\), got 'exr'"):
        FolderSink(tmp_path, HEADS, depth_format="exr")


@pytest.mark.parametrize("hw", [(1, 1), (1, 300), (300, 1), (2, 3)])
def test_the_folder_sink_writes_the_maps_of_a_frame_of_any_shape_at_that_shape(tmp_path, hw):
    """A 300x1 frame's depth PNG is 300x1, not transposed (``squeeze`` made it a vector, and a 1x1 one a scalar)."""
    import cv2

    from vpengine.io.sinks import FolderSink, load_depth

    rng = np.random.default_rng(3)
    depth = (rng.random(hw) * 5).astype(np.float32)
    results = [
        Result("depth", 0, 0.0, 0.01, {"depth": depth}, frame_size=hw),
        Result("seg", 0, 0.0, 0.01, {"classes": rng.integers(0, 3, hw).astype(np.uint8)}, frame_size=hw),
        Result("det", 0, 0.0, 0.01, head_results(0)[2].outputs, frame_size=hw),
    ]
    sink = FolderSink(tmp_path, HEADS, viz=True)
    for r in results:
        sink.write(r, rng.integers(0, 256, (*hw, 3), dtype=np.uint8), "f0")
    sink.close()
    got = load_depth(tmp_path / "depth", "f0")
    assert got.shape == hw and np.abs(got - depth).max() <= (depth.max() - depth.min()) / 65534 + 1e-6
    assert cv2.imread(str(tmp_path / "seg" / "f0.png"), cv2.IMREAD_UNCHANGED).shape == hw
    for h in HEADS:
        assert cv2.imread(str(tmp_path / h / "viz" / "f0.jpg")).shape == (*hw, 3)


def test_a_file_that_cannot_be_written_raises_from_close_naming_it(tmp_path):
    from vpengine.io.sinks import FolderSink

    sink = FolderSink(tmp_path, HEADS)
    (tmp_path / "seg").rmdir()
    (tmp_path / "seg").write_text("a file where the head's folder was")
    sink.write(head_results(0)[1], None, "f0")  # written on a file thread (Note [Parallel file writes])
    with pytest.raises(OSError, match=r"cannot write '.*/seg/f0.png'"):  # loudly, not cv2's False
        sink.close()


def test_a_failed_file_write_is_raised_by_a_later_write_and_every_write_that_returned_is_on_disk(tmp_path):
    from vpengine.io.sinks import FILE_WRITERS, FolderSink

    sink = FolderSink(tmp_path, HEADS)
    (tmp_path / "seg").rmdir()
    (tmp_path / "seg").write_text("a file where the head's folder was")
    returned = []
    with pytest.raises(OSError, match=r"cannot write '.*/seg/f0.png'"):
        sink.write(head_results(0)[1], None, "f0")
        for i in range(1, 2 * FILE_WRITERS + 2):  # no more files than that are in the works at once
            sink.write(head_results(i)[0], None, f"f{i}")
            returned.append(f"f{i}")
    sink.close()
    assert sorted(p.stem for p in (tmp_path / "depth").glob("*.png")) == returned
    scales = tmp_path / "depth" / "depth_scale.jsonl"  # none yet when the very first depth write raised
    lines = scales.read_text().splitlines() if scales.exists() else []
    assert [json.loads(x)["frame"] for x in lines] == returned  # a scale line for every PNG, and only for those


def test_the_folder_sink_writes_its_files_off_the_callers_thread(tmp_path, monkeypatch):
    from vpengine.io import sinks

    threads = set()
    imwrite = sinks._imwrite

    def recording(*args):  # type: ignore[no-untyped-def]
        threads.add(threading.current_thread().name)
        imwrite(*args)

    monkeypatch.setattr(sinks, "_imwrite", recording)
    sink = sinks.FolderSink(tmp_path, HEADS)
    for i in range(6):
        for r in head_results(i):
            sink.write(r, None, f"f{i}")
    sink.close()
    assert threads and threading.current_thread().name not in threads
    assert len(list((tmp_path / "depth").glob("*.png"))) == len(list((tmp_path / "seg").glob("*.png"))) == 6


def test_annotated_pictures_wait_for_every_head_and_fill_a_missing_one_with_its_newest_result(tmp_path):
    import cv2

    from vpengine.io.sinks import AnnotatedSink

    frame = np.full((60, 80, 3), 90, np.uint8)
    sink = AnnotatedSink(HEADS, pictures=tmp_path / "p", video=tmp_path / "v.mp4", fps=10, lag=2)
    drawn = []
    sink_draw = sink._draw
    sink._draw = lambda fid: (drawn.append(fid), sink_draw(fid))  # type: ignore[method-assign]
    for r in head_results(0):
        sink.write(r, frame, "f0")
    assert drawn == [0]  # every head answered: drawn at once
    depth1, seg1, _ = head_results(1)
    sink.write(depth1, frame, "f1")
    sink.write(seg1, frame, "f1")  # det skips frame 1 (a lower rate)
    for i in (2, 3):
        sink.write(head_results(i)[0], frame, f"f{i}")
    assert drawn == [0, 1]  # frame 1 once two newer frames wait
    # frames of another size are letterboxed into the video's size, never stretched
    for r in head_results(4):
        sink.write(r, np.full((120, 60, 3), 200, np.uint8), "f4")
    sink.close()
    assert drawn == [0, 1, 2, 3, 4]
    assert sorted(p.name for p in (tmp_path / "p").iterdir()) == [f"f{i}.jpg" for i in range(5)]
    cap = cv2.VideoCapture(str(tmp_path / "v.mp4"))
    assert cap.get(cv2.CAP_PROP_FRAME_COUNT) == 5 and cap.get(cv2.CAP_PROP_FPS) == 10
    first = cv2.imread(str(tmp_path / "p" / "f0.jpg"))
    assert (cap.get(cv2.CAP_PROP_FRAME_WIDTH), cap.get(cv2.CAP_PROP_FRAME_HEIGHT)) == first.shape[1::-1]
    cap.release()
    # the det tile of frame 1 shows frame 0's boxes, not 'no result yet'
    f0, f1 = first, cv2.imread(str(tmp_path / "p" / "f1.jpg"))
    h, w = f0.shape[0] // 2, f0.shape[1] // 2
    assert np.abs(f1[h:, w:].astype(int) - f0[h:, w:]).mean() < 2


def test_an_annotated_sink_needs_somewhere_to_write():
    from vpengine.io.sinks import AnnotatedSink

    with pytest.raises(ValueError, match="needs a pictures folder, a video file or both"):
        AnnotatedSink(HEADS)
    with pytest.raises(ValueError, match="video rate must be a number of Hz above 0, got 0"):
        AnnotatedSink(HEADS, video="x.mp4", fps=0)
