"""What every backend shares: the executor contract and precision handling.

Note [Executor contract]
~~~~~~~~~~~~~~~~~~~~~~~~
An executor computes a batch of frames in one call (Note [Batched models] in models/base.py): it is called with
``{name: tensor}`` holding every input of the model's ``input_spec`` with a leading batch dimension ``B``,
``1 <= B <= max_batch`` (``make_executor(..., max_batch=N)``, default 1), the same ``B`` for every input, and returns
``{name: tensor}`` holding every output of its ``output_spec`` with the same leading ``B`` (same names, and per frame
the declared shapes and dtypes). One frame is a batch of one: ``t.unsqueeze(0)``, a view. The returned tensors may be
the executor's own static buffers (CUDA graphs, ONNX Runtime IO binding): they are valid until the next call, and
the caller copies them out before calling again -- the worker copies them into the output slot at once
(``WorkerCore._run_model``). Inputs are only read, never kept: the worker passes views into mailbox slots whose
addresses change from call to call. Executors are called from one thread at a time. Backends with static buffers
(compile, onnx) hold them for ``max_batch`` frames and refuse a larger batch, naming the limit; eager takes any.

Note [Slot-bound runs]
~~~~~~~~~~~~~~~~~~~~~~
Mailbox slots are allocated once, at start, at fixed addresses, so an executor may prepare to run straight from
them: ``bind(inputs, outputs)`` is handed every input slot's tensors and every output slot's tensors (lists indexed
like the rings' slots; one frame each, no batch dimension) and returns True if it will take ``run_bound(i, j)`` --
run the batch of one frame in input slot ``i``, write output slot ``j``, both enqueued on the current stream --
instead of a call followed by the worker's own copies. The compile backend binds on CUDA: it captures, per slot, a
small CUDA graph of the copies into the static inputs of its batch-of-one graph and out of its static outputs, so a
frame costs three graph launches instead of one copy launch per tensor (a DPT head reads eight feature tensors), each
of which holds Python's interpreter lock in thread mode. The base class binds nothing.

Note [Precision]
~~~~~~~~~~~~~~~~
``precision`` (fp32 | fp16 | bf16) is the dtype a model computes in. Recipes declare their specs in that dtype
(``ctx.dtype_name``) but may build their weights in float32, and many keep host-facing outputs in float32 or
integers (depth maps, class ids, boxes) and call ``.float()`` on their inputs for numerically touchy parts. A backend
honours the precision by (1) casting the model's floating-point parameters to the dtype (half the memory and
bandwidth), with the buffers of the modules that own them (batch-norm statistics), while buffers of parameter-free
modules stay as built: normalisation means and anchor grids lose nothing to fp16/bf16 rounding (``cast_model_``),
(2) running it under ``torch.autocast`` for that dtype, so matmuls and convolutions run in the low precision even
where the model mixes in float32 tensors, while autocast keeps reductions such as softmax in float32 where it knows
they need it, and (3) casting every output to its declared dtype, so the mailbox layout planned from the specs holds
whatever autocast chose inside. Recipes that cast themselves to ``ctx.dtype`` lose nothing: step (1) is then a no-op.
"""

from __future__ import annotations

import abc
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, ClassVar

import torch

from vpengine.backends.options import BackendError, BackendOptions
from vpengine.models.base import Model
from vpengine.specs import PRECISION_DTYPES, SpecDict, format_specs


def precision_dtype(precision: str, name: str) -> torch.dtype:
    """The torch dtype of a precision name; BackendError naming the accepted ones otherwise."""
    try:
        return PRECISION_DTYPES[precision]
    except KeyError:
        raise BackendError(
            f"{name}: unknown precision {precision!r}; accepted: {', '.join(PRECISION_DTYPES)}"
        ) from None


def resolve_device(device: torch.device | str) -> torch.device:
    """``cuda`` -> ``cuda:N`` (the current device), so it compares equal to a tensor's device."""
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        return torch.device("cuda", torch.cuda.current_device())
    return device


class PrecisionRunner:
    """Run ``fn`` under autocast for ``dtype`` and cast its outputs to their declared dtypes (Note [Precision])."""

    def __init__(
        self,
        fn: Callable[[dict[str, torch.Tensor]], dict[str, torch.Tensor]],
        output_spec: SpecDict,
        dtype: torch.dtype,
        device_type: str,
    ) -> None:
        self.fn = fn
        self.out_dtypes = {k: s.torch_dtype for k, s in output_spec.items()}
        self.dtype = dtype
        self.device_type = device_type
        self.autocast = dtype != torch.float32

    def __call__(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        with torch.autocast(self.device_type, dtype=self.dtype, enabled=self.autocast):
            out = self.fn(inputs)
        # .to() returns the tensor itself when the dtype already matches: free in the fp32 case.
        return {k: (v.to(self.out_dtypes[k]) if k in self.out_dtypes else v) for k, v in out.items()}


def cast_model_(model: Model, dtype: torch.dtype) -> Model:
    """Cast ``model`` to ``dtype`` in place, the way Note [Precision] says: floating-point parameters, and the
    floating-point buffers of modules that own parameters (batch-norm statistics must match their weights).
    Buffers of parameter-free modules -- normalisation constants, anchor grids -- stay as the recipe built them."""
    if dtype == torch.float32:
        return model
    for module in model.modules():
        params = [p for _, p in module.named_parameters(recurse=False)]
        if not params:
            continue
        for p in params:
            if p.is_floating_point():
                p.data = p.data.to(dtype)
        for name, b in list(module.named_buffers(recurse=False)):
            if b.is_floating_point():
                setattr(module, name, b.to(dtype))
    return model


class Executor(abc.ABC):
    """Runs one model: ``executor(inputs) -> outputs`` with the model's named specs (Note [Executor contract]).

    One constructor for every backend (``make_executor`` calls it): it checks and keeps what they share, then
    ``_setup`` does the backend's own work (cast, compile, export, capture). ``opts``: the backend's options (None:
    their defaults); ``cache_dir``: the folder whose subfolders hold what a backend keeps on disk (ONNX exports,
    compile caches)."""

    backend: ClassVar[str]
    #: The class of this backend's ``backend_options``.
    options: ClassVar[type[BackendOptions]]

    def __init__(
        self,
        model: Model,
        device: torch.device | str,
        precision: str,
        name: str,
        opts: BackendOptions | None,
        max_batch: int,
        cache_dir: Path,
        progress: Callable[[int, int], None] | None = None,
    ) -> None:
        self.name = name
        # (steps done, steps in all) after each step of a long set-up: Note [Start progress] in supervisor.py
        self.progress: Callable[[int, int], None] = progress or (lambda done, total: None)
        self.device = resolve_device(device)
        self.precision = precision
        self.dtype = precision_dtype(precision, name)
        if not isinstance(max_batch, int) or max_batch < 1:
            raise BackendError(f"{name}: max_batch must be a whole number >= 1, got {max_batch!r}")
        self.max_batch = max_batch
        self.input_spec: SpecDict = dict(model.input_spec)
        self.output_spec: SpecDict = dict(model.output_spec)
        self.opts = opts if opts is not None else self.options.model_validate({})
        self.cache_dir = cache_dir
        self._setup(model)

    @abc.abstractmethod
    def _setup(self, model: Model) -> None:
        """The backend's own set-up of ``model`` (built on the device, in eval mode), all of it before READY."""

    @abc.abstractmethod
    def __call__(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Run the model on a batch of ``inputs``; see Note [Executor contract] for shapes and the outputs' lifetime."""

    def bind(self, inputs: list[dict[str, torch.Tensor]], outputs: list[dict[str, torch.Tensor]]) -> bool:
        """Prepare ``run_bound`` over these input and output slots (Note [Slot-bound runs]); False: not supported."""
        return False

    def run_bound(self, in_index: int, out_index: int) -> None:
        """Run on input slot ``in_index`` into output slot ``out_index`` (after a ``bind`` that returned True)."""
        raise BackendError(f"{self.name}: the {self.backend} backend does not run from bound slots")

    def run_bound_on(self, stream: torch.cuda.Stream | None, in_index: int, out_index: int) -> None:
        """``run_bound`` queued on ``stream`` from a thread whose current stream is another one (Note [Launch
        path] in runtime/handoff.py)."""
        if stream is None:
            self.run_bound(in_index, out_index)
            return
        with torch.cuda.stream(stream):
            self.run_bound(in_index, out_index)

    def held_bytes(self) -> int:
        """Device memory this executor holds alone through PyTorch's allocator, 0 off CUDA: its model's weights and
        buffers, and what its backend keeps besides (``CompiledExecutor``: its CUDA graphs' pool and static inputs).
        Not what it borrows while it runs (an eager model's activations come from its process's cache and go back
        there) nor ONNX Runtime's own allocations."""
        if self.device.type != "cuda":
            return 0
        model = getattr(self, "model", None)
        return tensor_bytes([*model.parameters(), *model.buffers()]) if isinstance(model, torch.nn.Module) else 0

    def describe(self) -> dict[str, Any]:
        """Facts for logs and stats (backend, precision, and what the backend chose)."""
        return {
            "backend": self.backend,
            "precision": self.precision,
            "device": str(self.device),
            "max_batch": self.max_batch,
        }

    def _batch(self, inputs: dict[str, torch.Tensor], keys: list[str]) -> int:
        """The batch size of ``inputs`` (the ``keys`` of them the model reads), checked: each is ``[B, *spec]`` of
        its spec's dtype, with one ``B`` from 1 to ``max_batch`` (Note [Executor contract])."""
        batch = None
        for key in keys:
            t = inputs.get(key)
            spec = self.input_spec[key]
            if t is None:
                raise BackendError(
                    f"{self.name}: input {key!r} is missing; the model reads {format_specs(self.input_spec)}"
                )
            if t.dim() != len(spec.shape) + 1 or t.shape[1:] != spec.shape or t.dtype != spec.torch_dtype:
                raise BackendError(
                    f"{self.name}: input {key!r} is {t.dtype}{list(t.shape)}, the model was built for a batch of "
                    f"{spec} frames: {spec.dtype}[{', '.join(['B', *map(str, spec.shape)])}]"
                )
            if batch is None:
                batch = t.shape[0]
            elif t.shape[0] != batch:
                raise BackendError(
                    f"{self.name}: input {key!r} holds {t.shape[0]} frames but {keys[0]!r} holds {batch}; "
                    "every input needs the same batch size"
                )
        if batch is None or not 1 <= batch <= self.max_batch:
            raise BackendError(
                f"{self.name}: a batch of {batch} frames; the {self.backend} backend was set up for 1 to "
                f"{self.max_batch} (make_executor's max_batch)"
            )
        return batch

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, {', '.join(f'{k}={v}' for k, v in self.describe().items())})"


def tensor_bytes(tensors: Iterable[torch.Tensor]) -> int:
    """The bytes of the distinct CUDA storages under ``tensors`` (views of one storage count once)."""
    seen: dict[int, int] = {}
    for t in tensors:
        if t.is_cuda:
            storage = t.untyped_storage()
            seen[storage.data_ptr()] = storage.nbytes()
    return sum(seen.values())
