"""Named tensor specs: the vocabulary shared by models, mailboxes and the engine.

A model declares ``input_spec`` and ``output_spec`` as ``{name: TensorSpec}``. The engine checks a whole
pipeline against these at build time and preallocates every mailbox slot from them, so nothing is allocated per
frame. A spec describes one frame and carries no batch dimension: models compute batches of frames, each tensor
with a leading batch dimension in front of its spec's shape (Note [Batched models] in models/base.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

_TORCH_DTYPES: dict[str, torch.dtype] = {
    "float32": torch.float32,
    "float16": torch.float16,
    "bfloat16": torch.bfloat16,
    "float64": torch.float64,
    "uint8": torch.uint8,
    "int8": torch.int8,
    "int16": torch.int16,
    "int32": torch.int32,
    "int64": torch.int64,
    "bool": torch.bool,
}
#: The dtype a model computes in for each ``precision`` of the config (Note [Precision] in backends/base.py).
PRECISION_DTYPES: dict[str, torch.dtype] = {
    "fp32": torch.float32,
    "fp16": torch.float16,
    "bf16": torch.bfloat16,
}


@dataclass(frozen=True)
class TensorSpec:
    """Shape and dtype of one named tensor. ``dtype`` is a torch dtype name such as ``"float32"``."""

    shape: tuple[int, ...]
    dtype: str

    def __post_init__(self) -> None:
        if self.dtype not in _TORCH_DTYPES:
            raise ValueError(f"unknown dtype {self.dtype!r}; accepted: {sorted(_TORCH_DTYPES)}")
        shape = tuple(int(s) for s in self.shape)
        if any(s < 0 for s in shape):
            raise ValueError(f"negative dimension in shape {shape}")
        object.__setattr__(self, "shape", shape)

    @property
    def torch_dtype(self) -> torch.dtype:
        return _TORCH_DTYPES[self.dtype]

    @property
    def itemsize(self) -> int:
        return torch.empty((), dtype=self.torch_dtype).element_size()

    @property
    def numel(self) -> int:
        return math.prod(self.shape)

    @property
    def nbytes(self) -> int:
        return self.numel * self.itemsize

    def matches(self, t: torch.Tensor | np.ndarray) -> bool:
        if isinstance(t, np.ndarray):
            return tuple(t.shape) == self.shape and str(t.dtype) == self.dtype
        return tuple(t.shape) == self.shape and t.dtype == self.torch_dtype

    def __str__(self) -> str:
        return f"{self.dtype}[{', '.join(map(str, self.shape))}]"

    def to_json(self) -> dict[str, Any]:
        return {"shape": list(self.shape), "dtype": self.dtype}


SpecDict = dict[str, TensorSpec]


def dtype_name(dtype: torch.dtype) -> str:
    for name, d in _TORCH_DTYPES.items():
        if d == dtype:
            return name
    raise ValueError(f"unsupported dtype {dtype}")


def format_specs(specs: SpecDict) -> str:
    return ", ".join(f"{k}: {v}" for k, v in specs.items()) or "(none)"


def specs_nbytes(specs: SpecDict) -> int:
    return sum(s.nbytes for s in specs.values())
