"""Thread mode's device mailboxes name their device with its index ("cuda:0"), as process mode's do, so a head
whose features are on its own device reads them there (Note [One call for a batch's copies] in runtime/worker.py):
a frame alone is its slot, viewed; a batch of several cameras' frames goes into the batch buffers in one call. A
ring made for a bare "cuda" used to keep that name, which compares unequal to a worker's "cuda:0", and every head of
a thread-mode engine then copied each frame and key of a batch on its own, and a frame alone into a buffer. Run on
the GPU machine: ``pytest -m gpu tests/gpu``."""

from __future__ import annotations

import pytest
import torch

from helpers.rings import submitter
from tests_paths import tiny
from vpengine.runtime.control import ControlBlock
from vpengine.runtime.device import DeviceContext
from vpengine.runtime.lanes import make_lanes
from vpengine.runtime.worker import WorkerCore, WorkerSpec
from vpengine.specs import TensorSpec
from vpengine.transport.memory import allocate
from vpengine.transport.ring import ReaderDecl, SlotRing

pytestmark = [pytest.mark.gpu, pytest.mark.usefixtures("require_cuda")]

F = {"x": TensorSpec((4,), "float32"), "y": TensorSpec((4,), "float32")}  # the features (submitter fills x and y)
D = {"d": TensorSpec((4,), "float32")}


def test_a_local_region_for_bare_cuda_names_the_current_device():
    region = allocate("t", 64, "cuda", shared=False)
    try:
        assert region.device == torch.device("cuda", torch.cuda.current_device())
        assert region.tensor().device == region.device
    finally:
        region.close()


def _head(cameras: list[str]):
    """A head worker of ``cameras`` on thread mode's rings (not shared) made for "cuda", with a model that notes
    each batch it is given and the address of its ``x``."""
    cams = "cameras=[" + ", ".join(f"{{name: {c}}}" for c in cameras) + "]" if len(cameras) > 1 else "cameras=[]"
    cfg = tiny("thread", "device=cuda", cams)
    n = len(cameras)
    slots = 2 * n + 1
    readers = [ReaderDecl(f"depth@{c}" if n > 1 else "depth", "latest", tag=i) for i, c in enumerate(cameras)]
    in_ring = SlotRing.create("in", F, slots, readers, device="cuda", shared=False, n_tags=n)
    out_ring = SlotRing.create("out", D, slots, [ReaderDecl("peek")], device="cuda", shared=False, n_tags=n)
    lanes = make_lanes(cfg)
    spec = WorkerSpec(
        name="depth",
        role="head",
        config=cfg.model_dump(mode="json"),
        upstream=F,
        upstream_meta={},
        lanes=lanes.of("depth"),
        in_ring=in_ring.desc,
        out_ring=out_ring.desc,
        notify_output=False,
    )
    seen: list[tuple[torch.Tensor, int]] = []

    def model(inputs):
        seen.append((inputs["x"].clone(), inputs["x"].data_ptr()))
        return {"d": inputs["x"] * 5}

    control = ControlBlock.create(lanes.control_names())
    core = WorkerCore(spec, model, D, in_ring, out_ring, control, DeviceContext("cuda"))
    return core, seen, in_ring, out_ring


def test_a_frame_alone_is_read_in_its_slot():
    core, seen, in_ring, out_ring = _head(["front"])
    try:
        submitter(in_ring, ["front"])("front", 3.0)
        core._take()
        torch.cuda.synchronize()
        ((x, ptr),) = seen
        assert torch.equal(x, torch.full((1, 4), 3.0, device=x.device))
        slot_ptrs = {in_ring.views[i]["x"].data_ptr() for i in range(len(in_ring.views))}
        assert ptr in slot_ptrs  # the slot itself, not a copy in a batch buffer
    finally:
        core.run(lambda: True)
        in_ring.close()
        out_ring.close()


def test_a_batch_of_several_cameras_is_copied_in_one_call(monkeypatch):
    cameras = ["front", "left", "rear"]
    core, seen, in_ring, out_ring = _head(cameras)
    calls: list[int] = []
    foreach = torch._foreach_copy_

    def counted(dsts, srcs, **kw):
        calls.append(len(dsts))
        return foreach(dsts, srcs, **kw)

    monkeypatch.setattr(torch, "_foreach_copy_", counted)
    try:
        submit = submitter(in_ring, cameras)
        for c, v in zip(cameras, (1.0, 2.0, 3.0)):
            submit(c, v)
        core._take()
        torch.cuda.synchronize()
        ((x, _),) = seen
        assert torch.equal(x, torch.tensor([[1.0] * 4, [2.0] * 4, [3.0] * 4], device=x.device))
        # the inputs' call: every key of every frame (2 x 3); then the outputs' (1 x 3), device to device too
        assert calls == [6, 3], calls
    finally:
        core.run(lambda: True)
        in_ring.close()
        out_ring.close()
