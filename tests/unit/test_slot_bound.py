"""The worker's slot-bound path (Note [Slot-bound runs]) on the CPU: an executor that binds is handed every slot of
its rings at start and told, per frame, which input slot to read and which output slot to write.

The compile backend binds only on CUDA (tests/gpu/test_compile_cuda.py); here a wrapper around the eager executor
binds on the CPU, so the worker's side -- the slot indexes it passes, what it publishes -- is tested everywhere.
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

import vpengine.backends as backends
from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine

plain_make_executor = backends.make_executor


class Binding:
    """An eager executor that also runs from bound slots, recording which ones."""

    def __init__(self, inner) -> None:  # type: ignore[no-untyped-def]
        self.inner = inner
        self.output_spec = inner.output_spec
        self.used: Counter[tuple[int, int]] = Counter()

    def __call__(self, inputs):  # type: ignore[no-untyped-def]
        return self.inner(inputs)

    def held_bytes(self) -> int:
        return self.inner.held_bytes()

    def bind(self, inputs, outputs) -> bool:  # type: ignore[no-untyped-def]
        self.inputs, self.outputs = inputs, outputs
        return True

    def run_bound(self, i: int, j: int) -> None:
        self.used[(i, j)] += 1
        # a slot's one frame as a batch of one; host frames on CUDA
        out = self.inner({k: v.to(self.inner.device)[None] for k, v in self.inputs[i].items()})
        for k, t in self.outputs[j].items():
            t.copy_(out[k][0])


@pytest.fixture
def binding(monkeypatch):
    made: dict[str, Binding] = {}

    def make(model, backend, device, name, **kw):  # type: ignore[no-untyped-def]
        made[name] = Binding(plain_make_executor(model, backend, device, name, **kw))
        return made[name]

    monkeypatch.setattr(backends, "make_executor", make)
    return made


def run(cfg, n: int) -> dict[int, dict[str, dict[str, np.ndarray]]]:  # type: ignore[no-untyped-def]
    out = {}
    with Engine(cfg) as e:
        for i in range(n):
            res = e.wait(e.submit(frame(i), frame_id=i), timeout=10)
            assert set(res) == {"depth", "seg", "det"}, (i, sorted(res))
            out[i] = {h: {k: np.array(v) for k, v in r.outputs.items()} for h, r in res.items()}
    return out


def test_bound_workers_publish_what_unbound_ones_do_and_use_every_slot(binding):
    n = 12
    bound = run(tiny("thread"), n)
    assert set(binding) == {"foundation", "depth", "seg", "det"}
    for name, ex in binding.items():
        assert sum(ex.used.values()) == n, name
        # the rings rotate: several input and output slots were read and written
        assert len({i for i, _ in ex.used}) >= 2 and len({j for _, j in ex.used}) >= 2, (name, ex.used)
    binding.clear()
    backends.make_executor = plain_make_executor  # the same engine unbound (monkeypatch restores it either way)
    plain = run(tiny("thread"), n)
    for i in range(n):
        for head, outs in plain[i].items():
            for k, v in outs.items():
                np.testing.assert_array_equal(bound[i][head][k], v, err_msg=f"frame {i} {head}.{k}")
