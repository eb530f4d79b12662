"""A DINOv2 backbone in the running engine: a real camera frame in, a depth map at input resolution out.

The backbone is a tiny "custom" DINOv2 with random (seeded) weights, so the engine's output can be recomputed
in this process and compared, in thread mode and in process mode (where the weights are built in another process).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from tests_paths import DEVICE, MEDIA
from vpengine.config import load_config
from vpengine.engine import Engine
from vpengine.models.build import build_model
from vpengine.runtime.plan import make_plan

pytestmark = pytest.mark.timeout(180)

H, W = 270, 480  # a 1080p frame shrunk 4x keeps the run fast


def dinov2_cfg(mode: str, h: int = H, w: int = W, depth_heads: int = 1):
    return load_config(
        {
            "mode": mode,
            "device": DEVICE,
            "input": {"height": h, "width": w},
            "foundation_model": {
                "model": "dinov2_vits14",
                "options": {"size": "custom", "embed_dim": 48, "depth": 4, "heads": 3, "registers": 4},
                "preprocess": {"size": 140},
            },
            "heads": [
                {"name": "depth" if i == 0 else f"depth{i}", "model": "tiny_depth", "options": {"seed": i}}
                for i in range(depth_heads)
            ],
            "weights": {"random_weights": True},
        }
    )


@pytest.fixture(scope="module")
def cheetah() -> np.ndarray:
    img = cv2.imread(str(MEDIA / "cheetah_1080p_0.jpg"))
    assert img is not None and img.shape == (1080, 1920, 3)
    return np.ascontiguousarray(cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA))


def test_plan_of_the_run():
    plan = make_plan(dinov2_cfg("thread"))
    # 270x480 -> short side 140 -> 140x252 -> 10 x 18 tokens
    assert plan.feature_meta["grid"] == (10, 18) and plan.feature_meta["image_size"] == (140, 252)
    assert plan.feature_meta["backbone"] == "dinov2_vits14" and plan.feature_meta["embed_dim"] == 48
    assert str(plan.features["patch.3"]) == "float32[180, 48]"  # one frame, no batch dimension


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_engine_runs_dinov2_on_a_camera_frame(cheetah, mode):
    cfg = dinov2_cfg(mode)
    device = torch.device(cfg.device)
    plan = make_plan(cfg)
    fm = build_model(cfg, "foundation", "foundation", plan.frame_spec, {}, device, False)
    head = build_model(cfg, "depth", "head", plan.features, plan.feature_meta, device, False)
    with torch.inference_mode():
        feats = fm({"frame": torch.from_numpy(cheetah).to(device)[None]})  # a batch of one frame
        want = head({k: feats[k] for k in head.input_spec})["depth"][0].cpu().numpy()

    with Engine(cfg) as engine:
        fid = engine.submit(cheetah, timestamp=1700000000.5)
        out = engine.wait(fid, timeout=120)
        stats = engine.stats()
    r = out["depth"]
    depth = r["depth"]
    assert r.frame_id == fid and r.capture_time == 1700000000.5
    assert depth.shape == (H, W) and depth.dtype == np.float32
    assert np.isfinite(depth).all() and (depth > 0).all()
    # same seeded weights in the worker as here: the engine computed exactly this frame's depth
    np.testing.assert_allclose(depth, want, rtol=1e-4, atol=1e-6)
    assert stats["models"]["foundation"]["errors"] == 0 and stats["models"]["depth"]["errors"] == 0


def test_full_hd_depth_maps_of_several_heads_arrive_exact():
    """Two 1080p float32 depth maps a frame; a result kept by the caller never changes, a dropped one's memory is
    reused for a later frame."""
    img = cv2.imread(str(MEDIA / "cheetah_1080p_0.jpg"))
    flipped = np.ascontiguousarray(img[::-1])
    cfg = dinov2_cfg("process", 1080, 1920, depth_heads=2)
    device = torch.device(cfg.device)
    plan = make_plan(cfg)
    fm = build_model(cfg, "foundation", "foundation", plan.frame_spec, {}, device, False)
    heads = {h: build_model(cfg, h, "head", plan.features, plan.feature_meta, device, False) for h in plan.heads}
    want = {}
    with torch.inference_mode():
        for name, frame in (("upright", img), ("flipped", flipped)):
            feats = fm({"frame": torch.from_numpy(frame).to(device)[None]})  # a batch of one frame
            for h, m in heads.items():
                want[name, h] = m({k: feats[k] for k in m.input_spec})["depth"][0].cpu().numpy()
    assert not np.array_equal(want["upright", "depth"], want["upright", "depth1"])  # a swap of heads would show

    with Engine(cfg) as engine:
        kept = engine.wait(engine.submit(img), timeout=120)  # held through the frames below
        addresses = []
        for i in range(2):  # the first frame after the kept one, and one that takes a dropped one's place
            out = engine.wait(engine.submit(flipped if i % 2 == 0 else img), timeout=120)
            assert sorted(out) == ["depth", "depth1"]
            name = "flipped" if i % 2 == 0 else "upright"
            for h in heads:
                assert out[h]["depth"].shape == (1080, 1920)
                np.testing.assert_allclose(out[h]["depth"], want[name, h], rtol=1e-4, atol=1e-6)
            addresses.append(out["depth"]["depth"].ctypes.data)
            del out
    for h in heads:
        np.testing.assert_allclose(kept[h]["depth"], want["upright", h], rtol=1e-4, atol=1e-6)
    assert len(set(addresses)) == 1  # each frame's result reused the memory of the one dropped before it
