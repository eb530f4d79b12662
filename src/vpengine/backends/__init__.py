"""Execution backends: how a model runs. Each returns a callable with the model's dict-in/dict-out contract."""

from __future__ import annotations

from collections.abc import Callable

import torch

from vpengine.models.base import Model

Executor = Callable[[dict[str, torch.Tensor]], dict[str, torch.Tensor]]


def make_executor(model: Model, backend: str, device: torch.device, name: str) -> Executor:
    """The callable that runs ``model`` with ``backend`` ("eager", "compile", "onnx")."""
    if backend == "eager":
        return model
    raise ValueError(f"{name}: backend {backend!r} is not available in this build; accepted: 'eager'")
