"""Backends inside a running engine: an ONNX Runtime foundation model and a torch.compile head give the results an
all-eager engine gives for the same frames, in thread mode and in process mode (where export and compilation happen
in the worker processes, before READY)."""

from __future__ import annotations

import numpy as np
import pytest

from helpers.frames import frame
from helpers.groups import INDUCTOR
from tests_paths import tiny
from vpengine.config import ConfigError
from vpengine.engine import Engine

pytestmark = pytest.mark.timeout(600)

N_FRAMES = 6
THRESHOLD = 0.5  # tiny_det's default score threshold


def run_lockstep(cfg, n: int) -> dict[int, dict]:
    """Submit frames one at a time and wait for every head, so every model sees every frame."""
    out = {}
    with Engine(cfg) as e:
        heads = set(e.plan.heads)
        for i in range(n):
            fid = e.submit(frame(i), frame_id=100 + i)
            res = e.wait(fid, timeout=120)
            assert set(res) == heads, f"frame {fid}: results from {sorted(res)} only"
            out[i] = {h: r.outputs for h, r in res.items()}
        st = e.stats()
    for name, m in st["models"].items():
        assert m["errors"] == 0, (name, m)
    return out


def confident(det: dict, margin: float = 1e-3) -> list[tuple]:
    """Detections whose score is clearly above the threshold (a 1e-5 feature difference cannot flip them)."""
    keep = det["scores"] > THRESHOLD + margin
    return sorted(zip(map(tuple, det["boxes"][keep].tolist()), det["labels"][keep].tolist()))


# cropped, not resized: the CPU's fast 8-bit resize and an ONNX export's float resize differ by a grey level
EXACT = "foundation_model.preprocess.resize=none"


@pytest.fixture(scope="module")
def all_eager():
    """An all-eager engine's outputs for the frames. One run in thread mode serves both modes, which give identical
    outputs (tests/integration/test_pipeline.py::test_process_and_thread_mode_give_identical_outputs)."""
    return run_lockstep(tiny("thread", EXACT), N_FRAMES)


@INDUCTOR
@pytest.mark.parametrize("mode", ["thread", "process"])
def test_onnx_foundation_and_compiled_head_match_an_all_eager_engine(mode, all_eager, tmp_path, monkeypatch):
    want = all_eager
    cfg = tiny(
        mode,
        EXACT,
        "foundation_model.backend=onnx",
        "heads.depth.backend=compile",
    )
    monkeypatch.setenv("VPENGINE_CACHE", str(tmp_path))  # the workers (children in process mode) inherit it
    got = run_lockstep(cfg, N_FRAMES)

    entries = list((tmp_path / "onnx").glob("*/model.onnx"))
    assert (
        len(entries) == 1 and "TinyViT" in entries[0].parent.name
    )  # exported once, into the cache $VPENGINE_CACHE names
    for i in range(N_FRAMES):
        g, w = got[i], want[i]
        # ORT's features differ from PyTorch's by ~1e-5 of their scale (antialiased resize, reassociation).
        depth_scale = np.abs(w["depth"]["depth"]).max()
        np.testing.assert_allclose(
            g["depth"]["depth"], w["depth"]["depth"], rtol=1e-4, atol=1e-4 * depth_scale, err_msg=f"depth {i}"
        )
        differ = (g["seg"]["classes"] != w["seg"]["classes"]).mean()
        assert differ <= 1e-3, f"seg frame {i}: {differ:.3%} of pixels differ"  # argmax near-ties only
        assert confident(g["det"]) == confident(w["det"]), f"det frame {i}"
        assert abs(g["det"]["count"] - w["det"]["count"]) <= 1, f"det frame {i}"


def test_bad_backend_options_fail_the_plan_naming_the_accepted_ones():
    """While planning, before any worker starts (they used to fail in each worker, with a traceback)."""
    cfg = tiny("thread", "heads.seg.backend=compile", "heads.seg.backend_options={cuda_graph: false}")
    with pytest.raises(
        ConfigError,
        match=r"^heads.seg.backend_options: bad backend_options for backend 'compile': unknown key "
        r"'cuda_graph' \(accepted: compiler, cudagraphs, fullgraph, mode, slot_bound, warmup_iters\)$",
    ):
        Engine(cfg)
