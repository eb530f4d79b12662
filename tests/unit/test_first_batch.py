"""Note [First batch] (runtime/worker.py): before READY a worker runs one batch of a frame per camera through its own
copies and the model, into output slots it gives back unpublished, so that nothing a batch runs is run for the first
time on a served frame. Driven on real rings on the CPU (where ``prepare`` does not call it: it is device-agnostic),
for the foundation and for a head, which copies every feature key while its model reads some."""

from __future__ import annotations

import pytest
import torch

from helpers.rings import submitter
from tests_paths import tiny
from vpengine.models.base import ModelBuildError
from vpengine.runtime.control import ControlBlock
from vpengine.runtime.device import DeviceContext
from vpengine.runtime.lanes import make_lanes
from vpengine.runtime.worker import WorkerCore, WorkerSpec
from vpengine.specs import TensorSpec
from vpengine.transport.ring import ReaderDecl, SlotRing

CAMERAS = ["front", "left", "rear"]
X = {"x": TensorSpec((4,), "float32"), "y": TensorSpec((4,), "float32")}
F = {"f": TensorSpec((4,), "float32"), "g": TensorSpec((4,), "float32")}
D = {"d": TensorSpec((4,), "float32")}
SLOTS = 7  # readers + cameras + 1
EXAMPLE = {"x": torch.arange(4.0).unsqueeze(0), "y": torch.full((1, 4), 7.0)}


def _worker(role: str):
    """A worker of three cameras on real rings: the foundation (X in, F out; its model reads both keys) or a head
    (F in, all of it its upstream; its model reads ``f`` alone, D out). Its model notes every batch it is given."""
    cfg = tiny("thread", "cameras=[{name: front}, {name: left}, {name: rear}]")
    name = "foundation" if role == "foundation" else "depth"
    ins, outs = (X, F) if role == "foundation" else (F, D)
    readers = [ReaderDecl(f"{name}@{c}", "latest", tag=i) for i, c in enumerate(CAMERAS)]
    in_ring = SlotRing.create("in", ins, SLOTS, readers, n_tags=3)
    out_ring = SlotRing.create("out", outs, SLOTS, [ReaderDecl("peek")], n_tags=3)
    lanes = make_lanes(cfg)
    control = ControlBlock.create(lanes.control_names())
    spec = WorkerSpec(
        name=name,
        role="foundation" if role == "foundation" else "head",
        config=cfg.model_dump(mode="json"),
        upstream={} if role == "foundation" else F,
        upstream_meta={},
        lanes=lanes.of(name),
        in_ring=in_ring.desc,
        out_ring=out_ring.desc,
        notify_output=False,
    )
    batches: list[dict[str, torch.Tensor]] = []

    def model(inputs):
        batches.append({k: v.clone() for k, v in inputs.items()})
        if role == "foundation":
            return {"f": inputs["x"] * 2, "g": inputs["y"] * 3}
        return {"d": inputs["f"] * 5}

    core = WorkerCore(spec, model, outs, in_ring, out_ring, control, DeviceContext("cpu"))
    return core, batches, in_ring, out_ring, control


@pytest.fixture()
def foundation():
    core, batches, in_ring, out_ring, _ = _worker("foundation")
    submit = submitter(in_ring, CAMERAS)

    yield core, batches, submit, out_ring
    core.run(lambda: True)
    in_ring.close()
    out_ring.close()


def _untouched(out_ring: SlotRing, control: ControlBlock, entries: list[str]) -> None:
    """Nothing published, dropped or counted, and every slot free again."""
    st = out_ring.stats()
    assert (st["last_seq"], st["published"], st["dropped_newest"]) == (0, 0, 0), st
    for e in entries:
        assert [control.get(e, k) for k in ("runs", "batches", "dropped", "skipped")] == [0, 0, 0, 0], e
    writer = out_ring.writer()
    taken = [writer.acquire(timeout=0) for _ in range(SLOTS)]
    assert all(s is not None for s in taken)
    for s in taken:
        writer.abort(s)  # type: ignore[arg-type]


def test_the_foundation_runs_a_batch_of_every_camera_once_and_publishes_nothing(foundation):
    core, batches, submit, out_ring = foundation
    assert core.warm_batch(EXAMPLE) == 3
    assert len(batches) == 1  # one model call: a frame per camera, each the example
    assert torch.equal(batches[0]["x"], EXAMPLE["x"].expand(3, 4))
    assert torch.equal(batches[0]["y"], EXAMPLE["y"].expand(3, 4))
    # the outputs were copied into the slots it then gave back
    written = [out_ring.views[i]["f"] for i in range(SLOTS)]
    assert sum(torch.equal(t, 2 * EXAMPLE["x"][0]) for t in written) == 3
    _untouched(out_ring, core.control, [lane.entry for lane in core.lanes])
    # and the worker serves as before: a batch of the three cameras' frames, each its own output
    ids = [submit(c, v) for c, v in zip(CAMERAS, (1.0, 2.0, 3.0))]
    core._take()
    peek = out_ring.reader("peek")
    for fid, v in zip(ids, (1.0, 2.0, 3.0)):
        slot, _ = peek.pin_origin(fid)
        assert slot is not None
        assert slot.tensors["f"][0].item() == 2 * v and slot.tensors["g"][0].item() == 3 * (v + 0.5)
        peek.release(slot)
    assert out_ring.last_seq == 3


def test_a_head_whose_model_reads_some_feature_keys_copies_them_all():
    core, batches, in_ring, out_ring, control = _worker("head")
    try:
        only_f = {"f": torch.full((1, 4), 0.25)}  # the head's model reads f; the worker copies f and g
        assert core.warm_batch(only_f) == 3
        assert len(batches) == 1 and set(batches[0]) == {"f", "g"}
        assert torch.equal(batches[0]["f"], only_f["f"].expand(3, 4))
        g = batches[0]["g"]  # random values of its spec, the same for every frame
        assert g.shape == (3, 4) and torch.equal(g[0], g[2]) and bool(((g >= 0) & (g < 1)).all())
        assert sum(torch.equal(out_ring.views[i]["d"], torch.full((4,), 1.25)) for i in range(SLOTS)) == 3
        _untouched(out_ring, control, [lane.entry for lane in core.lanes])
    finally:
        core.run(lambda: True)
        in_ring.close()
        out_ring.close()


def test_a_ring_published_to_before_is_left_alone(foundation):
    core, batches, submit, out_ring = foundation
    submit("front", 1.0)
    core._take()
    assert out_ring.last_seq == 1
    assert core.warm_batch(EXAMPLE) == 0 and len(batches) == 1  # the served frame's call alone


def test_a_model_that_fails_on_the_batch_fails_the_start_naming_it(foundation):
    core, _, _, out_ring = foundation

    def broken(inputs):
        raise RuntimeError("out of memory at a batch of 3")

    core.model = broken
    with pytest.raises(
        ModelBuildError,
        match=r"foundation: a batch of 3 example frames, run before READY .*"
        r"raised RuntimeError: out of memory at a batch of 3",
    ):
        core.warm_batch(EXAMPLE)
    _untouched(out_ring, core.control, [lane.entry for lane in core.lanes])  # its slots given back


def test_a_device_error_on_the_batch_is_raised_as_it_is(foundation):
    core, _, _, out_ring = foundation

    def lost(inputs):
        raise RuntimeError("CUDA error: an illegal memory access was encountered")

    core.model = lost
    with pytest.raises(RuntimeError, match="CUDA error") as info:
        core.warm_batch(EXAMPLE)
    assert not isinstance(info.value, ModelBuildError)  # the device's, not the config's
    assert any("example frames run before READY" in n for n in info.value.__notes__)
    _untouched(out_ring, core.control, [lane.entry for lane in core.lanes])


def test_example_inputs_short_of_a_key_the_worker_reads_are_refused_by_name(foundation):
    core, batches, _, out_ring = foundation  # its upstream names no keys here: nothing fills y
    with pytest.raises(ModelBuildError, match=r"foundation: example inputs lack \['y'\], which the worker reads"):
        core.warm_batch({"x": EXAMPLE["x"]})
    assert not batches and out_ring.last_seq == 0
