"""Execution backends: how a model runs. Each returns an executor with the model's dict-in/dict-out contract.

* ``eager``: the PyTorch model as written.
* ``compile``: ``torch.compile`` (inductor); on CUDA replayed as one CUDA graph per batch size over static buffers
  (Note [CUDA graphs] in ``compiled.py``).
* ``onnx``: an ONNX export, cached on disk (Note [ONNX cache key] in ``onnx_export.py``), run by ONNX Runtime with
  IO binding.

Every backend honours the model's precision (Note [Precision] in ``base.py``) and does all its compilation,
export, autotuning and graph capture inside ``make_executor``, which the worker calls before it reports READY.
Options per model come from the config's ``backend_options`` and are validated by the backend (``options.py``).
Backends are imported lazily, so onnxruntime is only needed by models that use it.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch

from vpengine.backends.base import Executor, precision_dtype
from vpengine.backends.options import BackendError, backend_names, parse_options
from vpengine.models.base import Model
from vpengine.models.catalog import cache_dir as catalog_cache_dir
from vpengine.specs import PRECISION_DTYPES

__all__ = ["PRECISION_DTYPES", "BackendError", "Executor", "backend_names", "make_executor", "parse_options"]

#: Each backend's executor class, imported when first used (optional dependencies stay optional).
_EXECUTORS = {
    "eager": ("vpengine.backends.eager", "EagerExecutor"),
    "compile": ("vpengine.backends.compiled", "CompiledExecutor"),
    "onnx": ("vpengine.backends.onnxrt", "OnnxExecutor"),
}


def make_executor(
    model: Model,
    backend: str,
    device: torch.device | str,
    name: str,
    *,
    options: Mapping[str, Any] | None = None,
    precision: str = "fp32",
    cache_dir: str | Path | None = None,
    max_batch: int = 1,
    progress: Callable[[int, int], None] | None = None,
) -> Executor:
    """The executor that runs ``model`` (built on ``device``, in eval mode) with ``backend``.

    ``options`` are the model's ``backend_options``, ``precision`` its fp32/fp16/bf16 setting, ``cache_dir`` a
    cache folder (ONNX exports go to its ``onnx`` subfolder, compile caches to its ``compile`` subfolder: Note
    [Compile cache key] in ``compile_cache.py``; None: the checkpoint cache, ``catalog.cache_dir()``),
    ``max_batch`` the most frames one call computes (Note [Executor contract] in ``base.py``), ``progress`` called
    with (steps done, steps in all) as a long set-up goes (Note [Start progress] in ``runtime/supervisor.py``).
    Compilation, export and CUDA graph capture (for every batch size up to ``max_batch``) happen here. The eager
    and compile backends cast ``model`` to the precision in place and keep it; the onnx backend leaves it untouched
    and does not keep it.
    Raises BackendError (a ValueError) naming the model and the accepted values for a bad backend, option or
    precision, and carrying the underlying error when an export, compilation or capture fails.
    """
    opts = parse_options(backend, options, name)
    precision_dtype(precision, name)
    module, cls = _EXECUTORS[backend]
    executor: type[Executor] = getattr(importlib.import_module(module), cls)
    root = Path(cache_dir).expanduser() if cache_dir else catalog_cache_dir()
    return executor(model, device, precision, name, opts, max_batch, root, progress)
