"""Note [Inline launch] on CUDA: in thread mode the thread that submits a frame queues the foundation model's work on
the foundation's stream. Run on the GPU machine: ``pytest -m gpu tests/gpu``."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

from helpers.frames import frame
from helpers.inline import inline_launch
from tests_paths import tiny
from vpengine.engine import Engine

pytestmark = [pytest.mark.gpu, pytest.mark.timeout(900), pytest.mark.usefixtures("require_cuda")]
COMPILED = ["foundation_model.backend=compile", *[f"heads.{h}.backend=compile" for h in ("depth", "seg")]]


def run(
    inline: bool | None, *extra: str, n: int = 8, mode: str = "thread"
) -> tuple[dict[int, dict[str, dict[str, np.ndarray]]], int]:
    """n frames in lockstep; ``inline``: force the inline launch on or off (None: the engine decides)."""
    cfg = tiny(mode, "device=cuda", *extra)
    out = {}
    forced = contextlib.nullcontext() if inline is None else inline_launch(inline)
    with forced, Engine(cfg) as e:
        for i in range(n):
            res = e.wait(e.submit(frame(i), frame_id=i), timeout=120)
            assert set(res) == {"depth", "seg", "det"}, (inline, i, sorted(res))
            assert all(r.frame_id == i for r in res.values())
            out[i] = {h: {k: np.array(v) for k, v in r.outputs.items()} for h, r in res.items()}
        assert all(m["errors"] == 0 for m in e.stats()["models"].values())
        launches = e.stats()["engine"]["launched_by_submit"]
    return out, launches


def close(a, b) -> bool:  # type: ignore[no-untyped-def]
    return all(np.allclose(a[i][h][k], b[i][h][k], rtol=1e-4, atol=1e-4) for i in a for h in a[i] for k in a[i][h])


@pytest.mark.usefixtures("inductor_in_process")
def test_compiled_foundation_is_launched_by_submit_by_default_and_gives_the_same_results(monkeypatch):
    """auto: a slot-bound (compiled) foundation is launched from submit, with raw graph launches (Note [Launch
    path]); outputs as when its worker launches."""
    import vpengine.backends as backends

    made, plain = {}, backends.make_executor

    def make(model, backend, device, name, **kw):  # type: ignore[no-untyped-def]
        made[name] = plain(model, backend, device, name, **kw)
        return made[name]

    monkeypatch.setattr(backends, "make_executor", make)
    worker, none = run(False, *COMPILED)
    inline, launches = run(None, *COMPILED)
    assert none == 0 and launches >= 6  # lockstep: (nearly) every frame
    assert made["foundation"].describe()["raw_launch"] is True
    assert close(inline, worker)


def test_features_launched_by_submit_are_read_only_after_their_device_work(slow_foundation):
    """The submitting thread queues the foundation's work on the foundation's stream, before the slot's event: heads
    woken long before the slow features are there still read this frame's, as with the worker's own launch."""
    host, _ = run(None, mode="process")
    inline, launches = run(True)
    assert launches >= 6
    assert close(inline, host)
