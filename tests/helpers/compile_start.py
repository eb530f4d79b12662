"""A compile start in a process of its own (inductor's caches are per process): build a small model, make its
compile executor on the CPU, run it on fixed inputs and print the outputs and the executor's cache folder as JSON.
What the caches are is up to the environment the test gives it (VPENGINE_CACHE, TMPDIR, TORCHINDUCTOR_CACHE_DIR)."""

from __future__ import annotations

import json

import torch

from vpengine.backends import make_executor
from vpengine.models.base import Model
from vpengine.specs import TensorSpec


class Affine(Model):
    """``y = x @ w``, one small graph for inductor to trace and cache. Its one op runs as an extern kernel, so a
    start compiles no C++: a generated CPU kernel would cost each start a g++ run and the first one inductor's
    precompiled headers (~35 s of the test's ~50 s) and would be cached beside the graph, in the same folder."""

    def __init__(self) -> None:
        super().__init__()
        self.input_spec = {"x": TensorSpec((8,), "float32")}
        self.output_spec = {"y": TensorSpec((4,), "float32")}
        g = torch.Generator().manual_seed(0)
        self.w = torch.nn.Parameter(torch.randn(8, 4, generator=g))

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {"y": inputs["x"] @ self.w}


def example() -> dict[str, torch.Tensor]:
    """A batch of one input, the same in every process."""
    return {"x": torch.linspace(-1, 1, 8).unsqueeze(0)}


def main() -> None:
    ex = make_executor(Affine().eval(), "compile", "cpu", "affine")
    print(json.dumps({"y": ex(example())["y"].tolist(), "compile_cache": ex.describe()["compile_cache"]}))


if __name__ == "__main__":
    main()
