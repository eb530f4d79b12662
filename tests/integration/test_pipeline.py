"""A real multi-process pipeline: frame identity end to end, accounting, and thread/process equivalence."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from helpers.frames import frame
from tests_paths import DEVICE, tiny
from vpengine.engine import Engine
from vpengine.models.build import build_model
from vpengine.runtime.plan import make_plan

pytestmark = pytest.mark.timeout(180)


class Reference:
    """The same recipes built in this process: recompute what any frame's outputs must be."""

    def __init__(self, cfg):
        torch.set_num_threads(1)  # as in the workers, so float results are bit-identical on the CPU
        plan = make_plan(cfg)
        self.device = torch.device(cfg.device)
        self.fm = build_model(cfg, "foundation", "foundation", plan.frame_spec, {}, self.device, False)
        self.heads = {
            n: build_model(cfg, n, "head", plan.features, plan.feature_meta, self.device, False) for n in plan.heads
        }

    @torch.inference_mode()
    def __call__(self, img: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
        feats = self.fm({"frame": torch.from_numpy(img).to(self.device)[None]})  # a batch of one frame
        out = {}
        for name, head in self.heads.items():
            res = head({k: feats[k] for k in head.input_spec})
            out[name] = head.finalize({k: v[0].cpu().numpy() for k, v in res.items()})
        return out


def assert_same(got: dict, want: dict, what: str) -> None:
    """Bit-identical on the CPU; on a GPU, kernels may differ between processes in the last bits of floats."""
    assert set(got) == set(want), what
    for k in want:
        a, b = np.asarray(got[k]), np.asarray(want[k])
        if DEVICE == "cpu":
            np.testing.assert_array_equal(a, b, err_msg=f"{what}: {k}")
        elif a.dtype.kind == "f":
            np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5, err_msg=f"{what}: {k}")
        else:  # class ids / labels from an argmax: a near-tie may flip on a GPU
            assert a.shape == b.shape and (a == b).mean() >= 0.999, f"{what}: {k}"


def test_200_frames_three_heads_every_output_matches_its_frame():
    cfg = tiny("process")
    ref = Reference(cfg)
    results = []
    with Engine(cfg) as e:
        e.results()  # start the stream
        for i in range(200):  # faster than the models: they skip frames, which must be counted, never mixed up
            e.submit(frame(i), frame_id=5000 + i, timestamp=1000.0 + i)
            time.sleep(0.003)
            results += e.results()
        last = 5199
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            results += e.results(timeout=0.5)
            if {r.head for r in results if r.frame_id == last} == {"depth", "seg", "det"}:
                break
        time.sleep(0.2)
        results += e.results()
        st = e.stats()

    assert results, "no results"
    checked = {"depth": 0, "seg": 0, "det": 0}
    expected: dict[int, dict] = {}
    for r in results:
        i = r.frame_id - 5000
        assert 0 <= i < 200
        assert r.capture_time == 1000.0 + i  # the capture time travels with the frame
        if i not in expected:
            expected[i] = ref(frame(i))
        assert_same(r.outputs, expected[i][r.head], f"{r.head} frame {r.frame_id}")
        checked[r.head] += 1
    assert all(n >= 20 for n in checked.values()), checked

    fm = st["models"]["foundation"]
    assert fm["frames_seen"] == 200  # every submitted frame was either run or counted as skipped
    assert fm["runs"] + fm["skipped"] == 200
    for h in ("depth", "seg", "det"):
        m = st["models"][h]
        assert m["frames_seen"] == fm["runs"]  # each head saw every feature set: ran it or counted the skip
        assert m["runs"] + m["skipped"] + m["dropped"] == m["frames_seen"]
        res = st["results"][h]
        assert res["delivered"] + res["missed"] + res["pending"] == res["published"]
        assert res["delivered"] == checked[h]
        assert m["errors"] == 0 and m["restarts"] == 0


def _lockstep(mode: str, n: int) -> dict[tuple[str, int], dict]:
    out = {}
    with Engine(tiny(mode)) as e:
        for i in range(n):
            fid = e.submit(frame(i))
            for head, r in e.wait(fid, timeout=10).items():
                out[(head, fid)] = r.outputs
    return out


def test_process_and_thread_mode_give_identical_outputs():
    a = _lockstep("process", 30)
    b = _lockstep("thread", 30)
    assert set(a) == set(b) and len(a) == 90
    for key in a:
        assert_same(a[key], b[key], str(key))
