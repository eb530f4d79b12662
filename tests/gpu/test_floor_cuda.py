"""The floor experiment's device times by batch size (``bench paper --experiments floor --floor-batches``) on CUDA:
each model's device time, the models back to back and batches pipelined, for batches of as many frames as an engine of that many
cameras runs, and the pipelined batches' outputs. Run on the GPU machine: ``pytest -m gpu tests/gpu/test_floor_cuda.py``."""

from __future__ import annotations

import pytest

from tests_paths import TINY
from vpengine.bench.paper import floor
from vpengine.bench.paper.harness import Bench, InProcess

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.timeout(600),
    pytest.mark.usefixtures("require_cuda", "inductor_in_process"),
]

OVERRIDES = ["mode=thread", "device=cuda", "foundation_model.backend=compile", "heads.depth.backend=compile"]


def test_the_floor_gives_each_batch_sizes_device_times_and_a_frames_share():
    b = Bench.load(TINY, OVERRIDES, frames=5)
    out = floor.run(b, b.images(2), ("depth", "seg"), (4, 1, 4))
    assert sorted(out["by_batch"]) == ["1", "4"]  # each size once
    for got in out["by_batch"].values():
        assert set(got["device_ms"]) == {"foundation", "depth", "seg"}
        assert all(v > 0 for v in got["device_ms"].values()), got
        # batches pipelined still run their backbones one after another on one stream: no faster than that
        assert got["pipelined_ms"] >= 0.9 * got["device_ms"]["foundation"], got
        assert got["separate_pipelined_ms_a_frame"] > 0 and got["batching_gain"] > 0, got
    one = out["by_batch"]["1"]  # the batch-of-one floor, not measured twice
    assert one["device_ms"] == out["device_ms"] and one["chained_ms"] == out["chained_ms"]["compute"]
    assert out["floor_sum_ms"] > 0 and out["thread"]["n"] == 5  # the engines as before


def test_a_batch_runs_each_frame_as_a_batch_of_one_does(monkeypatch):
    """The batch the floor times is the frame copied: the compiled foundation model's graph of 3 gives each copy
    the features its graph of 1 gives the frame (what is timed is the models' real work at that size). TF32 off:
    cuDNN may pick a TF32 convolution at one batch size and not at another."""
    import torch

    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    b = Bench.load(TINY, OVERRIDES, frames=1)
    seq = InProcess(b, [b.head("depth", "depth")], max_batch=3)
    img = b.images(1)[0]
    with torch.inference_mode():
        one = torch.from_numpy(img)[None].cuda()
        alone = {k: v.clone() for k, v in seq.fm({"frame": one}).items()}
        three = seq.fm({"frame": one.expand(3, *one.shape[1:]).contiguous()})
    for k, v in alone.items():
        for i in range(3):
            assert torch.allclose(three[k][i : i + 1], v, rtol=1e-3, atol=1e-3), k
    assert seq.device_times(img, n=5, batch=3)["foundation"] > 0
    assert seq._frame_runs[3]["frames"].shape[0] == 3  # what was timed read three frames


def test_batches_pipelined_give_each_frame_the_outputs_a_run_alone_gives():
    """What the pipelined floor times is the models' real work on the right data: three frames in turn through two
    feature buffers (so a head that read a buffer before the backbone's copy, or after the next one, would see another
    frame's features), and the outputs of the last batch are those of its frame run alone."""
    import numpy as np
    import torch

    from vpengine.bench.paper.harness import _Pipeline

    b = Bench.load(TINY, OVERRIDES, frames=1)
    seq = InProcess(b, [b.head("depth", "depth"), b.head("seg", "seg")], max_batch=2)
    imgs = [b.images(1)[0] // (k + 1) for k in range(3)]  # three different frames
    line = _Pipeline(seq, imgs, 2)
    with torch.inference_mode():
        line.after(torch.cuda.current_stream())
        for i in range(8):  # the last batch, 7, is frame 1
            line.issue(i)
        line.before(torch.cuda.current_stream())
        torch.cuda.synchronize()
        got = {name: [d.clone() for d in downs] for name, downs in line.downs.items()}
        x = torch.from_numpy(np.stack([imgs[1]] * 2)).cuda()
        feats = {k: v.clone() for k, v in seq.fm({"frame": x}).items()}
        for name, (head, keys) in seq.heads.items():
            want = [t.cpu() for t in head({k: feats[k] for k in keys}).values()]
            for g, w in zip(got[name], want, strict=True):
                assert torch.allclose(g.float(), w.float(), rtol=1e-4, atol=1e-4), name
        other = torch.from_numpy(np.stack([imgs[0]] * 2)).cuda()  # and not those of another frame
        feats0 = seq.fm({"frame": other})
        head, keys = seq.heads["depth"]
        assert not torch.allclose(got["depth"][0], head({k: feats0[k] for k in keys})["depth"].cpu())
