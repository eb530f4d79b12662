"""Small user-style models for tests: build-time checks, and a foundation model that notes its threads."""

from __future__ import annotations

import fcntl
import os
import threading
import time
from typing import Any, ClassVar

import torch

from vpengine.models.base import BuildContext, Model
from vpengine.models.tiny import TinyDepthHead, TinyDetHead, TinyHeadOptions, TinySegHead, TinyViT
from vpengine.models.weights import apply_state_dict, configured_or_default, read_state_dict, resolve_checkpoint
from vpengine.specs import TensorSpec


class SmallHead(Model):
    """A user head on a 4x8 float32 ``x``, giving a 4x8 ``y`` (per frame): subclasses write ``forward``, which gets
    ``x: [B, 4, 8]`` and returns ``y: [B, 4, 8]`` (Note [Batched models])."""

    role = "head"

    def __init__(self) -> None:
        super().__init__()
        self.input_spec = {"x": TensorSpec((4, 8), "float32")}
        self.output_spec = {"y": TensorSpec((4, 8), "float32")}


class SharedDeviceHead(TinyDepthHead):
    """tiny_depth whose every run holds, for ``hold_ms``, an exclusive lock on the file ``lock`` (its options) that
    every such head shares, in any thread or process: a make-believe device that a few heads over-subscribe the way
    heads share one GPU, sleeping rather than spending the test machine's cores."""

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        m = cls(ctx, TinyHeadOptions())
        m.lock_path, m.hold_s = str(ctx.cfg.options["lock"]), float(ctx.cfg.options["hold_ms"]) / 1e3
        m.fd = -1  # opened on the first run, in the worker's own process
        return m

    def forward(self, inputs):  # type: ignore[no-untyped-def]
        if self.fd < 0:
            self.fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o600)
        fcntl.flock(self.fd, fcntl.LOCK_EX)
        try:
            time.sleep(self.hold_s)
        finally:
            fcntl.flock(self.fd, fcntl.LOCK_UN)
        return super().forward(inputs)

    def __del__(self) -> None:
        if getattr(self, "fd", -1) >= 0:
            os.close(self.fd)


class NeedsMissingFeature(Model):
    role = "head"

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        m = cls()
        m.input_spec = {"patch.9": TensorSpec((16, 32), "float32")}  # one frame: specs have no batch dimension
        m.output_spec = {"y": TensorSpec((), "float32")}
        return m


class TrainedElsewhere(TinyDepthHead):
    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        m = cls(ctx, TinyHeadOptions())
        m.meta["trained_on"] = "dinov2_vitl14"
        return m


class ThreadNotingViT(TinyViT):
    """tiny_vit that notes the name of the thread each of its runs happens in (thread mode: one process), and
    whether inference mode was on."""

    threads: ClassVar[list[str]] = []
    inference: ClassVar[list[bool]] = []

    def forward(self, inputs):  # type: ignore[no-untyped-def]
        ThreadNotingViT.threads.append(threading.current_thread().name)
        ThreadNotingViT.inference.append(torch.is_inference_mode_enabled())
        return super().forward(inputs)


class StreamNotingDepth(TinyDepthHead):
    """tiny_depth that notes the priority of the CUDA stream each of its runs is queued on (eager, CUDA)."""

    priorities: ClassVar[list[int]] = []

    def forward(self, inputs):  # type: ignore[no-untyped-def]
        StreamNotingDepth.priorities.append(torch.cuda.current_stream().priority)
        return super().forward(inputs)


class EdgeBoxesDet(TinyDetHead):
    """tiny_det that finds, on every frame, one box of zero width on the left edge and one real box: a head's own
    empty box (Note [Empty boxes] in engine/boundary.py), not one made by mapping to a smaller frame."""

    def forward(self, inputs):  # type: ignore[no-untyped-def]
        out = super().forward(inputs)
        b = out["boxes"].shape[0]
        out["boxes"][:, :2] = torch.tensor([[0.0, 10.0, 0.0, 30.0], [20.0, 10.0, 60.0, 50.0]])
        out["scores"][:, :2] = torch.tensor([0.9, 0.8])
        out["labels"][:, :2] = torch.tensor([1, 2], dtype=torch.int32)
        out["count"] = torch.full((b,), 2, dtype=torch.int32)
        return out


class OwnWeightsHead(TinyDepthHead):
    """A user head that gets its weights its own way in ``load_checkpoint`` (here: fixed values; in life a file
    beside its code or a download of its own) and declares no checkpoint, so the engine has nothing to check."""

    loaded: ClassVar[list[str]] = []

    def load_checkpoint(self, ctx: BuildContext) -> None:
        with torch.no_grad():
            self.proj.weight.fill_(0.5)
        OwnWeightsHead.loaded.append(ctx.name)


class DeclaredCheckpointHead(TinyDepthHead):
    """A user head that loads the checkpoint its config names, else its default catalog name ``my_site_depth``,
    declared once (``needed_checkpoint``) for both the engine's check and its ``load_checkpoint``."""

    def needed_checkpoint(self, cfg: Any) -> str | None:
        return configured_or_default(cfg, "my_site_depth")

    def load_checkpoint(self, ctx: BuildContext) -> None:
        path = resolve_checkpoint(ctx, self)
        if path is not None:
            apply_state_dict(self, read_state_dict(path), str(path), ctx.name)


class RaisingHead(TinyDepthHead):
    """A user head whose own code fails as it is built (a feature key it expected)."""

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Any:
        raise KeyError("patch.7")


class NoSuperInitHead(TinyDepthHead):
    """A user head whose __init__ forgot super().__init__()."""

    def __init__(self, ctx: BuildContext, opts: Any) -> None:
        pass


class MaskSegHead(TinySegHead):
    """A user segmentation head modelled on a zoo head, its class map named ``mask`` (not ``classes``)."""

    def __init__(self, ctx: BuildContext, opts: Any) -> None:
        super().__init__(ctx, opts)
        self.output_spec = {"mask": self.output_spec["classes"]}
        self.meta = {**self.meta, "output_grid": {"mask": "labels"}}

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {"mask": super().forward(inputs)["classes"]}


class ReturnsNothingHead(TinyDepthHead):
    """A user head whose from_config forgot its return."""

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Any:
        super().from_config(ctx)
