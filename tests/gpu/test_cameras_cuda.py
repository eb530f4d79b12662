"""Several cameras on CUDA with compiled models (Note [Cameras] in runtime/worker.py): the frames of the cameras
run as one batch through a graph captured for that batch size, and each frame's outputs equal what the frame gives
alone. Run on the GPU machine: ``pytest -m gpu tests/gpu``."""

from __future__ import annotations

import numpy as np
import pytest

from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.timeout(900),
    pytest.mark.usefixtures("require_cuda", "inductor_in_process"),
]

COMPILED = ["foundation_model.backend=compile", *[f"heads.{h}.backend=compile" for h in ("depth", "seg")]]
CAMERAS = ["cameras=[{name: front}, {name: left}, {name: rear}]", "runtime.batch_window_ms=100"]


@pytest.mark.parametrize("mode", ["thread", "process"])
def test_compiled_batches_of_cameras_give_what_each_frame_gives_alone(mode):
    with Engine(tiny(mode, "device=cuda", *COMPILED, *CAMERAS)) as e:
        alone = [e.wait(e.submit(frame(i), camera="front"), timeout=60) for i in range(3)]
        for _ in range(6):
            for i in range(3):
                ids = [e.submit(frame(i + k), camera=c) for k, c in ((0, "front"), (4, "left"), (9, "rear"))]
                outs = [e.wait(f, timeout=60) for f in ids]
                for head, key in (("depth", "depth"), ("seg", "classes"), ("det", "boxes")):
                    np.testing.assert_allclose(outs[0][head][key], alone[i][head][key], rtol=1e-3, atol=1e-4)
                assert [o["depth"].camera for o in outs] == ["front", "left", "rear"]
        models = e.stats()["models"]
        assert models["foundation"]["batched"] >= 27, models["foundation"]  # of 54 frames
        assert models["depth"]["batched"] >= 27, models["depth"]
        assert models["foundation"]["errors"] == 0 and models["foundation"]["dropped"] == 0
