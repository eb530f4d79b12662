"""Eager PyTorch: the model as written, at its precision (Note [Precision])."""

from __future__ import annotations

import torch

from vpengine.backends.base import Executor, PrecisionRunner, cast_model_
from vpengine.backends.options import EagerOptions
from vpengine.models.base import Model


class EagerExecutor(Executor):
    """Calls the model directly, on a batch of any size. Outputs are fresh tensors from the caching allocator (reused
    blocks after warm-up).

    The model is cast to the precision in place: the executor owns it from here on.
    """

    backend = "eager"
    options = EagerOptions

    def _setup(self, model: Model) -> None:
        self.model = cast_model_(model, self.dtype)
        self._run = PrecisionRunner(self.model, self.output_spec, self.dtype, self.device.type)

    def __call__(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        with torch.inference_mode():
            return self._run(inputs)
