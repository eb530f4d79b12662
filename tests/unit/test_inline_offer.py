"""Note [Inline launch], the offer alone: what ``InlineLaunch.launch`` does for the thread that publishes a frame,
with a stand-in worker (the engine-level behaviour is in tests/integration/test_inline_launch.py)."""

from __future__ import annotations

from vpengine.runtime.worker import InlineLaunch


class Control:
    def __init__(self) -> None:
        self.hz: float | None = None

    def rate(self, name: str) -> float | None:
        return self.hz


class Reader:
    def __init__(self) -> None:
        self.pins: list[str] = []

    def pin(self, timeout: float = 0.0) -> str | None:
        self.pins.append("frame")
        return "frame"


class Worker:
    name = "foundation"

    def __init__(self, fail: bool = False) -> None:
        self.control, self.reader, self.fail = Control(), Reader(), fail
        self.launched: list[tuple[object, object]] = []

    def _launch(self, slot: object, out: object) -> None:
        if self.fail:
            raise RuntimeError("launch failed")
        self.launched.append((slot, out))


def test_nothing_is_launched_unless_a_worker_is_armed():
    offer, worker = InlineLaunch(), Worker()
    assert offer.launch() is False
    offer.arm(worker, "out")  # type: ignore[arg-type]
    offer.disarm(worker)  # type: ignore[arg-type]
    assert offer.launch() is False and worker.reader.pins == [] and offer.take_done() is None


def test_an_armed_worker_gets_the_frame_pinned_launched_and_handed_over_once():
    offer, worker = InlineLaunch(), Worker()
    offer.arm(worker, "out")  # type: ignore[arg-type]
    assert offer.launch() is True
    assert worker.reader.pins == ["frame"] and worker.launched == [("frame", "out")] and offer.launches == 1
    slot, _, error = offer.take_done()  # type: ignore[misc]
    assert slot == "frame" and error is None
    assert offer.launch() is False  # disarmed by the launch: the next frame waits for the worker
    assert offer.take_done() is None and offer.launches == 1


def test_a_rate_changed_since_arming_leaves_the_frame_to_the_worker():
    offer, worker = InlineLaunch(), Worker()
    offer.arm(worker, "out")  # type: ignore[arg-type]
    worker.control.hz = 0.0  # paused after it armed, before it woke to disarm
    assert offer.launch() is False and worker.reader.pins == [] and worker.launched == []
    worker.control.hz = None  # the rate it armed under again
    assert offer.launch() is True and worker.launched == [("frame", "out")]


def test_a_launch_that_raises_is_handed_to_the_worker_not_raised_in_submit():
    offer, worker = InlineLaunch(), Worker(fail=True)
    offer.arm(worker, "out")  # type: ignore[arg-type]
    assert offer.launch() is True  # no exception here
    slot, _, error = offer.take_done()  # type: ignore[misc]
    assert slot == "frame" and isinstance(error, RuntimeError) and "launch failed" in str(error)
