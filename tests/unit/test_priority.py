"""runtime/priority.py: a lane's priority key as the control block holds it, and the least important of a model's
lanes (the one whose frame waits a batch when the model cannot keep up, Note [Cameras] in runtime/worker.py)."""

from __future__ import annotations

import pytest

from vpengine.runtime.control import ControlBlock
from vpengine.runtime.priority import least_important, priority_key

LANES = ["depth@front", "depth@side", "depth@rear"]  # one head's lanes, cameras in the configured order


@pytest.fixture()
def control():
    c = ControlBlock.create(LANES)
    yield c
    c.close()


def test_all_equal_the_camera_last_configured_is_the_least_important(control):
    assert priority_key(control, "depth@rear") == (0, 0)
    assert least_important(control, LANES) == 2


def test_a_lane_raised_gives_the_place_to_the_last_of_the_others(control):
    control.set("depth@rear", "priority", 1)  # set_priority("depth", 1, camera="rear")
    assert least_important(control, LANES) == 1


def test_a_cameras_priority_ranks_after_the_heads(control):
    control.set("depth@front", "camera_priority", -1)  # set_priority(None, -1, camera="front")
    assert least_important(control, LANES) == 0
    control.set("depth@front", "priority", 2)  # the head's priority comes first
    assert priority_key(control, "depth@front") == (2, -1)
    assert least_important(control, LANES) == 2
