"""The model interface: named tensors in, named tensors out, with the specs declared up front.

Every model the engine runs (preprocessing, the foundation model, heads, postprocessing, user heads) is a
:class:`Model`. It declares ``input_spec`` and ``output_spec`` (``{name: TensorSpec}``) in its constructor, from its
config alone, so the engine can build it on the ``meta`` device in the parent process, check the whole pipeline,
and size every mailbox before any weight is loaded or any worker is started.

A recipe (a ``Model`` subclass) is built through ``from_config(ctx)``, which may return a :class:`Pipeline` of
several models (preprocess -> backbone, head -> postprocess); the engine runs one recipe per worker.

Note [Batched models]
~~~~~~~~~~~~~~~~~~~~~
Specs describe ONE frame and carry no batch dimension anywhere: a frame is ``uint8[H, W, 3]``, DINOv2's features
``patch.i: float[h*w, C]`` and ``cls.i: float[C]``, a depth map ``float32[H, W]``, a detection count ``int32[]``.
A mailbox slot holds exactly one frame's tensors of these shapes (the layouts are planned from the specs).

``Model.forward`` computes a batch of frames in one go: it receives every input with a leading batch dimension
``B >= 1`` (``frame: [B, H, W, 3]``, ``patch.3: [B, h*w, C]``) and returns every output with the same leading ``B``
(``depth: [B, H, W]``, ``boxes: [B, M, 4]``, ``count: [B]``); ``check_outputs`` checks both. Frame ``i`` of the
outputs depends on frame ``i`` of the inputs only, and equals what a batch of that one frame gives (up to float
rounding of batched kernels): per-frame statistics (a colour map's min-max scaling) are taken per frame. Models
batch for real, one forward for the whole batch, not a Python loop over frames, except where a part cannot:
torchvision's proposal filtering and NMS in Faster R-CNN take lists with one entry per frame, and the ONNX backend
runs its batch-of-one export once per frame (``backends/onnxrt.py``).
``example_inputs(device, batch)`` makes such batched inputs; a single frame is a batch of one (``t.unsqueeze(0)``,
a view). ``finalize`` sees one frame's host outputs, as read from a slot: no batch dimension.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, ValidationError
from torch import nn

from vpengine.specs import PRECISION_DTYPES, SpecDict, dtype_name, format_specs

if TYPE_CHECKING:
    from vpengine.config import EngineConfig, ModelConfig

Role = Literal["foundation", "head"]


class ModelBuildError(ValueError):
    """A model cannot be built from its config (unknown recipe, bad options, mismatched inputs, bad checkpoint)."""


class Options(BaseModel):
    """Base of every recipe's options: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", protected_namespaces=())


@dataclass
class BuildContext:
    """What a recipe needs to build itself."""

    role: Role
    name: str
    cfg: ModelConfig
    engine: EngineConfig
    #: What the model reads: ``{"frame": ...}`` for the foundation model, the features for heads.
    upstream: SpecDict
    #: Facts about the upstream model (feature grid, embed dim, layers, backbone recipe, preprocessed size).
    upstream_meta: dict[str, Any] = field(default_factory=dict)
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    #: True in the parent while planning: build on the meta device, load no weights.
    plan_only: bool = False
    #: Recipe defaults merged under the user's options.
    defaults: dict[str, Any] = field(default_factory=dict)
    #: Whether the recipe read its ``postprocess`` block (``postprocess_options``): one it never reads is ignored.
    postprocess_read: bool = field(default=False, repr=False)

    @property
    def precision(self) -> str:
        return self.cfg.precision or self.engine.precision

    @property
    def dtype(self) -> torch.dtype:
        return PRECISION_DTYPES[self.precision]

    @property
    def dtype_name(self) -> str:
        return dtype_name(self.dtype)

    @property
    def input_hw(self) -> tuple[int, int]:
        return self.engine.input.height, self.engine.input.width

    @property
    def where(self) -> str:
        """This model's place in the config, as a config error names it: ``foundation_model`` or ``heads.NAME``."""
        return self.engine.model_path("foundation" if self.role == "foundation" else self.name)

    def options(self, cls: type[Options]) -> Any:
        merged = {**self.defaults, **self.cfg.options}
        try:
            return cls.model_validate(merged)
        except ValidationError as e:
            problems = []
            for err in e.errors():
                loc = ".".join([f"{self.where}.options", *map(str, err["loc"])])
                if err["type"] == "extra_forbidden":
                    problems.append(f"{loc}: unknown key (accepted: {', '.join(sorted(cls.model_fields))})")
                else:
                    msg = str(err["msg"]).removeprefix("Value error, ")
                    got = "" if ", got " in msg else f" (got {err.get('input')!r})"
                    problems.append(f"{loc}: {msg}{got}")
            raise ModelBuildError(f"bad options for {self.cfg.model!r}: {'; '.join(problems)}") from None

    def postprocess_options(self, cls: type[Options]) -> Any:
        self.postprocess_read = True
        raw = getattr(self.cfg, "postprocess", {}) or {}
        try:
            return cls.model_validate(raw)
        except ValidationError as e:
            problems = "; ".join(
                f"{'.'.join([f'{self.where}.postprocess', *map(str, err['loc'])])}: "
                f"{str(err['msg']).removeprefix('Value error, ')}"
                for err in e.errors()
            )
            raise ModelBuildError(
                f"bad postprocess options for {self.cfg.model!r}: {problems} "
                f"(accepted: {', '.join(sorted(cls.model_fields))})"
            ) from None

    def require(self, keys: list[str]) -> None:
        """Fail with the names involved if the upstream model does not produce ``keys``."""
        missing = [k for k in keys if k not in self.upstream]
        if missing:
            raise ModelBuildError(
                f"{self.name} ({self.cfg.model}) needs inputs {missing} which the upstream model does not produce; "
                f"it produces: {format_specs(self.upstream)}"
            )


class Model(nn.Module):
    """Base class: ``forward(dict[str, Tensor]) -> dict[str, Tensor]`` with declared specs."""

    #: Which slot of the pipeline a recipe can fill; None for building blocks (pre/postprocessing).
    role: ClassVar[Role | None] = None
    #: The torch.onnx exporter that ``backend_options.exporter: auto`` uses for a pipeline holding this model.
    #: "dynamo" (torch.export) unless the model has data-dependent shapes that torch.export cannot guard on.
    onnx_exporter: ClassVar[str] = "dynamo"

    input_spec: SpecDict
    output_spec: SpecDict

    def __init__(self) -> None:
        super().__init__()
        self.input_spec = {}
        self.output_spec = {}
        #: Facts for downstream models and users: grid size, labels, the backbone a head was trained on, ...
        self.meta: dict[str, Any] = {}

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        raise NotImplementedError(f"{cls.__name__} does not implement from_config")

    def needed_checkpoint(self, cfg: ModelConfig) -> str | None:
        """The checkpoint this model loads: a file path or catalog name, or None (the default) when it needs none
        or loads its own weights in :meth:`load_checkpoint`.

        The one place a model says so: the engine checks the answer on disk while planning, before any worker
        starts, and ``weights.resolve_checkpoint(ctx, self)`` in ``load_checkpoint`` turns it into the verified
        file. A recipe that cannot run without weights returns ``weights.configured_or_default(cfg, default)``:
        ``cfg.checkpoint``, else its default, else a CheckpointError saying that none is configured. Only asked when
        ``weights.random_weights`` is off.
        """
        return None

    def load_checkpoint(self, ctx: BuildContext) -> None:
        """Load this model's weights (usually from ``weights.resolve_checkpoint(ctx, self)``). Default: nothing."""

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:  # pragma: no cover - abstract
        raise NotImplementedError

    def finalize(self, outputs: dict[str, np.ndarray]) -> dict[str, Any]:
        """Host-side view for users of ONE frame's outputs, without a batch dimension (e.g. trim fixed-capacity
        detections to their count). Default: unchanged."""
        return outputs

    def example_inputs(self, device: torch.device | str = "cpu", batch: int = 1) -> dict[str, torch.Tensor]:
        """A batch of ``batch`` inputs of the declared specs, for warm-up and export (random, never zeros: zeros
        hide bugs; Note [Batched models])."""
        return random_inputs(self.input_spec, 0, batch, device)


class Pipeline(Model):
    """Models run one after another; each later model may read any key produced so far."""

    def __init__(self, *models: Model) -> None:
        super().__init__()
        if not models:
            raise ModelBuildError("a pipeline needs at least one model")
        self.stages = nn.ModuleList(models)
        available = {**models[0].input_spec, **models[0].output_spec}
        for m in models[1:]:
            for k, spec in m.input_spec.items():
                if k not in available:
                    raise ModelBuildError(
                        f"{type(m).__name__} needs input {k!r} ({spec}) that nothing before it produces; "
                        f"available: {format_specs(available)}"
                    )
                if available[k] != spec:
                    raise ModelBuildError(
                        f"{type(m).__name__} needs {k!r} as {spec} but it is produced as {available[k]}"
                    )
            available.update(m.output_spec)
        self.input_spec = dict(models[0].input_spec)
        self.output_spec = dict(models[-1].output_spec)
        for m in models:
            self.meta.update(m.meta)

    def needed_checkpoint(self, cfg: ModelConfig) -> str | None:
        # The stages share one config, so one checkpoint: the first stage that needs one names it.
        return next((n for m in self.stages if (n := m.needed_checkpoint(cfg)) is not None), None)  # type: ignore[operator]

    def load_checkpoint(self, ctx: BuildContext) -> None:
        for m in self.stages:
            m.load_checkpoint(ctx)  # type: ignore[operator]

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        values = dict(inputs)
        out: dict[str, torch.Tensor] = {}
        for m in self.stages:
            out = m({k: values[k] for k in m.input_spec})
            values.update(out)
        return out

    def finalize(self, outputs: dict[str, np.ndarray]) -> dict[str, Any]:
        return self.stages[-1].finalize(outputs)  # type: ignore[operator]


def random_inputs(
    spec: SpecDict, seed: int, batch: int = 1, device: torch.device | str = "cpu"
) -> dict[str, torch.Tensor]:
    """A batch of ``batch`` random tensors of ``spec`` (``[batch, *shape]``, Note [Batched models]), drawn on the
    CPU from ``seed`` so every device gets the same values: floats in [0, 1), integers in [0, 255) for uint8 and
    [0, 8) otherwise."""
    if batch < 1:
        raise ValueError(f"batch must be at least 1, got {batch}")
    g = torch.Generator().manual_seed(seed)
    out = {}
    for k, s in spec.items():
        shape = (batch, *s.shape)
        if s.torch_dtype.is_floating_point:
            t = torch.rand(shape, generator=g, device="cpu").to(s.torch_dtype)
        else:
            high = 255 if s.dtype == "uint8" else 8
            t = torch.randint(0, high, shape, generator=g, device="cpu").to(s.torch_dtype)
        out[k] = t.to(device)
    return out


def check_outputs(name: str, spec: SpecDict, outputs: dict[str, torch.Tensor], batch: int | None = None) -> None:
    """Raise naming the mismatch if a model's batched outputs differ from what it declared: every output must be
    ``[B, *shape]`` of its spec with one ``B`` for all (Note [Batched models]).

    ``batch``: how many frames the model was given. None: read off the outputs, from the first one with a dimension
    more than its spec; the message says where ``B`` came from, and writes ``B`` where no output has one.
    """
    missing = [k for k in spec if k not in outputs]
    assumed = f"a batch of {batch}: the frames the model was given"
    if batch is None:
        batched = [k for k in spec if k in outputs and outputs[k].dim() == len(spec[k].shape) + 1]
        if batched:
            batch = outputs[batched[0]].shape[0]
            assumed = f"a batch of {batch}: read off the leading dimension of {batched[0]!r}, as none was given"
        else:
            assumed = "B: none was given, and no output has a dimension in front of its declared shape to read it off"
    b = "B" if batch is None else str(batch)
    bad = [
        f"{k}: declared {spec[k]} per frame, so {spec[k].dtype}[{', '.join([b, *map(str, spec[k].shape)])}] "
        f"for a batch of {b}; got {outputs[k].dtype}{list(outputs[k].shape)}"
        for k in spec
        if k in outputs
        and not (
            outputs[k].dim() == len(spec[k].shape) + 1
            and outputs[k].shape[0] == batch
            and spec[k].matches(outputs[k][0])
        )
    ]
    if missing or bad:
        wrong = ([f"missing {missing}"] if missing else []) + bad
        raise ModelBuildError(f"{name}: outputs differ from the declared output_spec: {'; '.join(wrong)} ({assumed})")
