"""Note [Cameras], the worker side: a frame the model leaves for the next batch (it guessed it cannot keep up) is
kept, runs in the next batch and is answered then; only a newer frame of its camera replaces it. Driven one batch
at a time on real rings, the guess forced, so nothing depends on timing."""

from __future__ import annotations

import pytest

from helpers.rings import submitter
from tests_paths import tiny
from vpengine.runtime.control import ControlBlock
from vpengine.runtime.device import DeviceContext
from vpengine.runtime.lanes import make_lanes
from vpengine.runtime.worker import WorkerCore, WorkerSpec
from vpengine.specs import TensorSpec
from vpengine.transport.ring import ReaderDecl, SlotRing

CAMERAS = ["front", "rear"]
# two keys each way, so a batch's copies that mixed up keys and frames would show (Note [One call for a batch's copies])
X = {"x": TensorSpec((4,), "float32"), "y": TensorSpec((4,), "float32")}
F = {"f": TensorSpec((4,), "float32"), "g": TensorSpec((4,), "float32")}


@pytest.fixture()
def worker(request):
    mode = getattr(request, "param", "latest")  # the foundation's input_mode
    cfg = tiny("thread", "cameras=[{name: front}, {name: rear}]", f"foundation_model.input_mode={mode}")
    readers = [ReaderDecl(f"foundation@{c}", mode, tag=i) for i, c in enumerate(CAMERAS)]
    in_ring = SlotRing.create("input", X, 5, readers, n_tags=2)
    out_ring = SlotRing.create("features", F, 5, [ReaderDecl("peek")], n_tags=2)
    lanes = make_lanes(cfg)
    control = ControlBlock.create(lanes.control_names())
    spec = WorkerSpec(
        name="foundation",
        role="foundation",
        config=cfg.model_dump(mode="json"),
        upstream={},
        upstream_meta={},
        lanes=lanes.of("foundation"),
        in_ring=in_ring.desc,
        out_ring=out_ring.desc,
        notify_output=False,
    )

    def model(inputs):
        return {"f": inputs["x"] * 2, "g": inputs["y"] * 3}

    core = WorkerCore(spec, model, F, in_ring, out_ring, control, DeviceContext("cpu"))
    submit = submitter(in_ring, CAMERAS)

    def overloaded() -> None:
        """The model's last batches took longer than the cameras' frames come: it defers a frame."""
        core._batch_s = 1.0
        for lane in core.lanes:
            lane.mean_interval = 0.01

    def outputs(key: str = "f") -> dict[int, float]:
        """origin -> the value the model wrote for it as ``key``, of every output in the ring."""
        peek = out_ring.reader("peek")
        found = {}
        for origin in range(1, in_ring.last_seq + 1):
            slot, _ = peek.pin_origin(origin)
            if slot is not None:
                found[origin] = slot.tensors[key][0].item()
                peek.release(slot)
        return found

    def entry(camera: str, key: str) -> int:
        return control.get(lanes.select("foundation", camera)[0].entry, key)

    yield core, submit, overloaded, outputs, entry
    core.run(lambda: True)  # leaves at once, letting go of what it holds
    assert set(in_ring.pins().values()) == {-1}, in_ring.pins()  # -1: pins nothing
    in_ring.close()
    out_ring.close()


def test_a_deferred_frame_is_not_answered_and_runs_in_the_next_batch(worker):
    core, submit, overloaded, outputs, entry = worker
    front, rear = submit("front", 1.0), submit("rear", 2.0)
    overloaded()
    core._take()
    assert outputs() == {front: 2.0} and entry("rear", "deferred") == 1
    assert entry("rear", "decided") < rear  # not answered: a caller waiting for it keeps waiting
    core._take()  # nothing new came: the next batch is the deferred frame
    assert outputs() == {front: 2.0, rear: 4.0}
    assert entry("rear", "decided") == entry("rear", "last_run") == rear
    assert entry("rear", "runs") == 1 and entry("rear", "skipped") == 0


def test_a_newer_frame_of_its_camera_replaces_a_deferred_one_which_is_answered_skipped(worker):
    core, submit, overloaded, outputs, entry = worker
    submit("front", 1.0)
    old = submit("rear", 2.0)
    overloaded()
    core._take()
    new = submit("rear", 3.0)  # newest wins
    core._take()
    assert old not in outputs() and outputs()[new] == 6.0
    assert entry("rear", "skipped") == 1 and entry("rear", "runs") == 1
    assert entry("rear", "decided") == entry("rear", "last_run") == new


@pytest.mark.parametrize("worker", ["fifo"], indirect=True)
def test_a_model_that_reads_every_frame_runs_a_deferred_frame_before_the_newer_one_of_its_camera(worker):
    core, submit, overloaded, outputs, entry = worker
    submit("front", 1.0)
    old = submit("rear", 2.0)
    overloaded()
    core._take()
    new = submit("rear", 3.0)  # fifo: every frame, in order (Note [Frames in flight] in pipeline/pacing.py)
    core._take()
    assert outputs()[old] == 4.0 and new not in outputs()
    core._take()
    assert outputs()[new] == 6.0 and entry("rear", "skipped") == 0 and entry("rear", "runs") == 2


def test_a_deferred_frame_of_a_camera_paused_since_is_answered_and_let_go(worker):
    core, submit, overloaded, outputs, entry = worker
    submit("front", 1.0)
    rear = submit("rear", 2.0)
    overloaded()
    core._take()
    core.control.set_rate(core.lanes[1].entry, 0.0)  # rear's
    core.poll_s = 0.01
    core._take()
    assert rear not in outputs() and entry("rear", "decided") == rear and entry("rear", "skipped") == 1


def test_the_least_important_lane_as_priorities_are_now_is_the_one_deferred(worker):
    """Note [Cameras] with Note [Give way]'s key: rear (last in the configured order) waits a batch while the
    lanes are equal; once set_priority ranks rear above front, front's frame is the one that waits."""
    core, submit, overloaded, outputs, entry = worker
    front, _ = submit("front", 1.0), submit("rear", 2.0)
    overloaded()
    core._take()
    assert outputs() == {front: 2.0} and entry("rear", "deferred") == 1
    core._take()  # the deferred frame alone
    rear_entry = core.lanes[1].entry
    core.control.set(rear_entry, "priority", 5)  # the governor writes rear's most important head lane's here
    front2, rear2 = submit("front", 3.0), submit("rear", 4.0)
    overloaded()
    core._take()
    assert rear2 in outputs() and front2 not in outputs()
    assert entry("front", "deferred") == 1 and entry("rear", "deferred") == 1
    core._take()
    assert outputs()[front2] == 6.0 and entry("front", "decided") == front2


def test_a_cameras_priority_ranks_lanes_of_equal_head_priority(worker):
    core, submit, overloaded, outputs, entry = worker
    core.control.set(core.lanes[1].entry, "camera_priority", 2)  # rear's camera above front's
    _, rear = submit("front", 1.0), submit("rear", 2.0)
    overloaded()
    core._take()
    assert outputs() == {rear: 4.0} and entry("front", "deferred") == 1 and entry("rear", "deferred") == 0


def test_the_same_lane_is_never_deferred_twice_in_a_row(worker):
    core, submit, overloaded, outputs, entry = worker
    submit("front", 1.0), submit("rear", 2.0)
    overloaded()
    core._take()  # rear deferred
    core._take()  # rear's deferred frame alone: no choice to make
    front, rear = submit("front", 3.0), submit("rear", 4.0)
    overloaded()
    core._take()  # rear waited the last time: both run
    assert front in outputs() and rear in outputs() and entry("rear", "deferred") == 1
    submit("front", 5.0), submit("rear", 6.0)
    overloaded()
    core._take()  # and then rear may wait again
    assert entry("rear", "deferred") == 2


def test_a_deferred_frame_runs_while_a_lane_raised_above_it_since_defers_another(worker):
    """The frame deferred stays first in line: it runs in the next batch even when the lane least important now
    is another one, whose frame then waits instead."""
    core, submit, overloaded, outputs, entry = worker
    submit("front", 1.0)
    rear = submit("rear", 2.0)
    overloaded()
    core._take()  # rear deferred
    core.control.set(core.lanes[1].entry, "priority", 5)
    front = submit("front", 3.0)
    overloaded()
    core._take()  # front (now the least important) waits; rear's held frame runs
    assert outputs()[rear] == 4.0 and front not in outputs() and entry("front", "deferred") == 1
    core._take()
    assert outputs()[front] == 6.0 and entry("front", "skipped") == 0 and entry("rear", "skipped") == 0


def test_the_frames_of_one_batch_each_get_their_own_outputs(worker):
    # Note [One call for a batch's copies] in runtime/worker.py: one copy call for the whole batch, each pair in place
    core, submit, _, outputs, entry = worker
    front, rear = submit("front", 1.0), submit("rear", 2.0)
    core._take()
    assert outputs("f") == {front: 2.0, rear: 4.0}  # x * 2
    assert outputs("g") == {front: 4.5, rear: 7.5}  # y * 3, y = x + 0.5
    assert entry("front", "batched") == entry("rear", "batched") == 1
