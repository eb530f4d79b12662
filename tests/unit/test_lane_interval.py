"""Note [Cameras]: when a camera's next frame is due, which decides whether a batch waits for it, follows the
camera's rate within a few frames of a change, and one gap or burst does not move it."""

from __future__ import annotations

from vpengine.runtime.worker import _Lane

PERIOD = 1 / 30
WINDOW = 0.005  # runtime.batch_window_ms's default


def _lane(spacings: list[float]) -> tuple[_Lane, float]:
    """A lane whose frames came ``spacings`` apart, and when its last one came."""
    lane = _Lane(lane=None, reader=None, gate=None)  # type: ignore[arg-type]  # its timing alone
    t = 100.0
    lane.arrived(t)
    for s in spacings:
        t += s
        lane.arrived(t)
    return lane, t


def _waited_for(lane: _Lane, last: float) -> bool:
    """Whether a batch that starts with another camera's frame of the next tick, 2 ms before this camera's, waits
    for it: asked as a worker asks, when it has pinned that first frame."""
    now = last + PERIOD - 0.002
    return lane.due_by(now + WINDOW, now)


def test_a_camera_that_speeds_up_is_waited_for_within_three_frames():
    lane, last = _lane([0.08] * 10 + [PERIOD] * 3)  # a warm-up of frames one at a time, then the camera's 30 Hz
    assert abs(lane.interval - PERIOD) < 1e-9 and _waited_for(lane, last)


def test_one_gap_in_a_stream_does_not_stop_its_frames_being_waited_for():
    for gap in (0.5, 2.0, 30.0):  # a stream paused, a camera reconnecting
        lane, last = _lane([PERIOD] * 6 + [gap] + [PERIOD])
        assert _waited_for(lane, last), gap


def test_one_early_frame_does_not_make_the_next_look_due_early():
    lane, last = _lane([PERIOD] * 6 + [0.004])  # a driver that delivered two frames nearly at once
    now = last + 0.002
    assert not lane.due_by(now + WINDOW, now) and abs(lane.interval - PERIOD) < 1e-9


def test_a_camera_that_stopped_is_not_waited_for():
    lane, last = _lane([PERIOD] * 6)
    now = last + 4 * PERIOD  # no frame for four periods: not live
    assert not lane.due_by(now + WINDOW, now)
    assert not _lane([])[0].due_by(200.0, 100.0)  # one frame: no spacing known yet


def test_a_camera_handed_in_at_the_callers_pace_is_not_taken_for_stopped_after_one_longer_spacing():
    # frames 8 ms apart, once 30 ms (the caller busy with its results): 26 ms after the last, more than three of its
    # usual spacings, its next frame is still waited for
    lane, last = _lane([0.008] * 3 + [0.03] + [0.008] * 3)
    now = last + 0.026
    assert lane.due_by(now + 0.1, now)
