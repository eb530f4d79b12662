"""Note [First batch] (runtime/worker.py): before READY a worker runs one batch of a frame per camera through its own
copies and the model, into output slots it gives back unpublished, so that nothing a batch runs is run for the first
time on a served frame. Driven on real rings on the CPU (where ``prepare`` does not call it: it is device-agnostic)."""

from __future__ import annotations

import time

import pytest
import torch

from tests_paths import tiny
from vpengine.runtime.control import ControlBlock
from vpengine.runtime.device import DeviceContext
from vpengine.runtime.lanes import make_lanes
from vpengine.runtime.worker import WorkerCore, WorkerSpec
from vpengine.specs import TensorSpec
from vpengine.transport.ring import ReaderDecl, SlotRing

CAMERAS = ["front", "left", "rear"]
X = {"x": TensorSpec((4,), "float32"), "y": TensorSpec((4,), "float32")}
F = {"f": TensorSpec((4,), "float32"), "g": TensorSpec((4,), "float32")}
SLOTS = 7


@pytest.fixture()
def worker():
    cfg = tiny("thread", "cameras=[{name: front}, {name: left}, {name: rear}]")
    readers = [ReaderDecl(f"foundation@{c}", "latest", tag=i) for i, c in enumerate(CAMERAS)]
    in_ring = SlotRing.create("input", X, SLOTS, readers, n_tags=3)
    out_ring = SlotRing.create("features", F, SLOTS, [ReaderDecl("peek")], n_tags=3)
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
    batches: list[dict[str, torch.Tensor]] = []  # what the model was given, each call

    def model(inputs):
        batches.append({k: v.clone() for k, v in inputs.items()})
        return {"f": inputs["x"] * 2, "g": inputs["y"] * 3}

    core = WorkerCore(spec, model, F, in_ring, out_ring, control, DeviceContext("cpu"))
    writer = in_ring.writer()

    def submit(camera: str, value: float) -> int:
        slot = writer.acquire(timeout=1.0)
        assert slot is not None
        slot.tensors["x"].fill_(value)
        slot.tensors["y"].fill_(value + 0.5)
        now = time.monotonic()
        return writer.publish(slot, int(value), now, now, tag=CAMERAS.index(camera))

    yield core, batches, submit, out_ring
    core.run(lambda: True)
    in_ring.close()
    out_ring.close()


EXAMPLE = {"x": torch.arange(4.0).unsqueeze(0), "y": torch.full((1, 4), 7.0)}


def test_a_batch_of_every_camera_runs_once_and_publishes_nothing(worker):
    core, batches, submit, out_ring = worker
    assert core.warm_batch(EXAMPLE) == 3
    assert len(batches) == 1  # one model call: a frame per camera, each the example
    assert [list(t.shape) for t in batches[0].values()] == [[3, 4], [3, 4]]
    assert torch.equal(batches[0]["x"], EXAMPLE["x"].expand(3, 4)) and torch.equal(batches[0]["y"][2], EXAMPLE["y"][0])
    assert out_ring.last_seq == 0  # nothing published: no reader sees the warm batch
    writer = out_ring.writer()  # every slot was given back
    taken = [writer.acquire(timeout=0) for _ in range(SLOTS)]
    assert all(s is not None for s in taken)
    for s in taken:
        writer.abort(s)  # type: ignore[arg-type]
    # and the worker serves as before: a batch of the three cameras' frames, each its own output
    ids = [submit(c, v) for c, v in zip(CAMERAS, (1.0, 2.0, 3.0))]
    core._take()
    peek = out_ring.reader("peek")
    for fid, v in zip(ids, (1.0, 2.0, 3.0)):
        slot, _ = peek.pin_origin(fid)
        assert (
            slot is not None and slot.tensors["f"][0].item() == 2 * v and slot.tensors["g"][0].item() == 3 * (v + 0.5)
        )
        peek.release(slot)
    assert out_ring.last_seq == 3


def test_a_ring_published_to_before_is_left_alone(worker):
    core, batches, submit, out_ring = worker
    submit("front", 1.0)
    core._take()
    assert out_ring.last_seq == 1
    assert core.warm_batch(EXAMPLE) == 0 and len(batches) == 1  # the served frame's call alone


def test_example_inputs_without_a_key_the_worker_reads_are_refused_by_name(worker):
    core, batches, _, _ = worker
    with pytest.raises(ValueError, match=r"foundation: example inputs lack \['y'\]"):
        core.warm_batch({"x": EXAMPLE["x"]})
    assert not batches
