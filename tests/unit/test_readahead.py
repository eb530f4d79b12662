"""Frames read ahead on a thread of their own (Note [Read ahead] in io/readahead.py): the taker gets every frame in
order, a source's error at the frame it happened, a clean end, and the reader never runs further ahead than asked."""

from __future__ import annotations

import threading
import time
import traceback

import pytest

from vpengine.io.readahead import ReadAhead


class Counted:
    """A source of ``n`` numbered frames that records how many were read and on which thread, and fails at frame
    ``fail_at`` if given; ``closed`` is set by a generator's clean-up."""

    def __init__(self, n: int, fail_at: int | None = None) -> None:
        self.n, self.fail_at = n, fail_at
        self.read = 0
        self.threads: set[str] = set()
        self.closed = threading.Event()
        self.closed_on = ""

    def __iter__(self):  # type: ignore[no-untyped-def]
        try:
            for i in range(self.n):
                self.threads.add(threading.current_thread().name)
                if i == self.fail_at:
                    raise ValueError(f"cannot decode frame {i}")
                self.read += 1
                yield i
        finally:
            self.closed_on = threading.current_thread().name
            self.closed.set()


def wait_until(cond, timeout: float = 5.0) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


def test_every_frame_comes_in_order_read_on_another_thread_and_the_end_is_clean():
    src = Counted(100)
    frames = ReadAhead(src, ahead=3, name="reader-under-test")
    assert list(frames) == list(range(100))
    assert src.threads == {"reader-under-test"}
    with pytest.raises(StopIteration):  # ended for good
        next(frames)
    assert src.closed.wait(5)


def test_a_source_error_is_raised_at_its_frame_after_every_frame_before_it():
    src = Counted(10, fail_at=6)
    frames = ReadAhead(src, ahead=4)
    got = []
    with pytest.raises(ValueError, match="cannot decode frame 6") as err:
        for f in frames:
            got.append(f)
    assert got == [0, 1, 2, 3, 4, 5]
    assert "__iter__" in [f.name for f in traceback.extract_tb(err.value.__traceback__)]  # where the source raised
    with pytest.raises(StopIteration):
        next(frames)


def test_the_reader_runs_ahead_by_at_most_ahead_frames_while_the_taker_is_busy():
    src = Counted(50)
    frames = ReadAhead(src, ahead=3)
    wait_until(lambda: src.read >= 3)  # read before anyone asked
    time.sleep(0.1)
    assert src.read <= 3 + 1  # the queue's 3 and the one waiting for room
    assert next(frames) == 0
    wait_until(lambda: src.read >= 4)
    frames.close()


def test_at_most_limit_frames_are_read_from_the_source():
    src = Counted(50)
    frames = ReadAhead(src, ahead=8, limit=5)
    assert list(frames) == [0, 1, 2, 3, 4]
    assert src.closed.wait(5) and src.read == 5


def test_close_stops_the_reader_and_closes_the_source_on_its_thread():
    src = Counted(1000)
    frames = ReadAhead(src, ahead=2, name="reader-under-test")
    assert next(frames) == 0
    frames.close()
    assert src.closed.is_set() and src.closed_on == "reader-under-test"
    read = src.read
    time.sleep(0.05)
    assert src.read == read < 1000
    with pytest.raises(StopIteration):
        next(frames)


def test_ahead_must_be_at_least_one_frame():
    with pytest.raises(ValueError, match="got 0"):
        ReadAhead([], ahead=0)
