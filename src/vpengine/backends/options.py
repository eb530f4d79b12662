"""Per-backend options (``backend_options`` of a model's config block), validated strictly.

Each backend has one pydantic class; unknown keys and bad values fail with the model's name, the backend, the bad
key or value and what is accepted. This module imports no torch, so it stays cheap to import for config checks.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator


class BackendError(ValueError):
    """A model cannot run on the backend it was given: bad name, bad options, export or capture failure."""


class BackendOptions(BaseModel):
    """Base of every backend's options: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", frozen=True, protected_namespaces=())


class EagerOptions(BackendOptions):
    """Eager PyTorch has nothing to tune."""


class CompileOptions(BackendOptions):
    """``torch.compile`` (inductor), plus CUDA graphs over static buffers on CUDA devices."""

    mode: Literal["default", "max-autotune"] = Field(
        "default",
        description="Inductor optimisation level. max-autotune benchmarks kernel choices at warm-up (slow start). "
        "Inductor's own CUDA graphs are never used: vpengine captures its own (see cudagraphs).",
    )
    fullgraph: bool = Field(
        True,
        description="Fail at warm-up if the model has a graph break, instead of running parts of it eagerly.",
    )
    cudagraphs: bool = Field(
        True,
        description="On CUDA: capture the compiled model in one CUDA graph at warm-up and replay it per frame. "
        "Ignored on the CPU.",
    )
    slot_bound: bool = Field(
        True,
        description="With cudagraphs: also capture the copies in from and out to each mailbox slot as CUDA graphs "
        "(Note [Slot-bound runs]); false: the worker copies each tensor itself.",
    )
    warmup_iters: int = Field(
        3, ge=1, le=100, description="Compiled runs on a side stream before the CUDA graph is captured."
    )
    compiler: Literal["inductor", "aot_eager", "eager"] = Field(
        "inductor",
        description="torch.compile backend: inductor (generated kernels), aot_eager or eager (debugging).",
    )

    @model_validator(mode="after")
    def _mode_needs_inductor(self) -> CompileOptions:
        if self.mode != "default" and self.compiler != "inductor":
            raise ValueError(f"mode {self.mode!r} needs compiler 'inductor', got compiler {self.compiler!r}")
        return self


class OnnxOptions(BackendOptions):
    """Export to ONNX (cached on disk) and run with ONNX Runtime."""

    opset: int = Field(
        18,
        ge=17,
        le=23,
        description="ONNX opset of the export, 17..23. 18 (the default) is the first with antialiased Resize, which "
        "the preprocessing needs; TensorRT 10 reads it.",
    )
    exporter: Literal["auto", "dynamo", "torchscript"] = Field(
        "auto",
        description="torch.onnx exporter: dynamo (torch.export based, the maintained one), torchscript (legacy, "
        "tracing), or auto: the one the model asks for (torchscript for Faster R-CNN, whose NMS has data-dependent "
        "shapes; dynamo otherwise).",
    )
    providers: list[str] | None = Field(
        None,
        description="ONNX Runtime execution providers in priority order, e.g. [CUDAExecutionProvider, "
        "CPUExecutionProvider]; null: CUDA on a cuda device, CPU on the cpu.",
    )
    optimization: Literal["disable", "basic", "extended", "all"] = Field(
        "all", description="ONNX Runtime graph optimisation level."
    )
    intra_op_threads: int | None = Field(
        None,
        ge=1,
        le=256,
        description="ONNX Runtime intra-op threads; null: PyTorch's in this worker (the model's cpu_threads).",
    )
    verify: bool = Field(
        True,
        description="After a new export, run it on ONNX Runtime (CPU) against PyTorch on two inputs and refuse it if "
        "they disagree (catches graphs that froze a data-dependent value).",
    )
    cache: bool = Field(
        True,
        description="Reuse an earlier export from the cache when its key matches; false: export every start.",
    )


OPTIONS: dict[str, type[BackendOptions]] = {
    "eager": EagerOptions,
    "compile": CompileOptions,
    "onnx": OnnxOptions,
}


def backend_names() -> list[str]:
    """The accepted values of a model's ``backend`` field."""
    return list(OPTIONS)


def parse_options(backend: str, raw: Mapping[str, Any] | None, name: str) -> Any:
    """Validate ``raw`` as the options of ``backend`` for model ``name``; raise BackendError naming what is wrong."""
    cls = OPTIONS.get(backend)
    if cls is None:
        raise BackendError(f"{name}: unknown backend {backend!r}; accepted: {', '.join(repr(b) for b in OPTIONS)}")
    try:
        return cls.model_validate(dict(raw or {}))
    except ValidationError as e:
        accepted = ", ".join(sorted(cls.model_fields)) or "(none)"
        problems = []
        for err in e.errors():
            loc = ".".join(str(p) for p in err["loc"]) or "backend_options"
            if err["type"] == "extra_forbidden":
                problems.append(f"unknown key {loc!r} (accepted: {accepted})")
            else:
                problems.append(f"{loc}: {err['msg']} (got {err.get('input')!r})")
        raise BackendError(f"{name}: bad backend_options for backend {backend!r}: {'; '.join(problems)}") from None
