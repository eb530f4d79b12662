"""DINOv2's linear semantic segmentation heads (ADE20K, PASCAL VOC 2012), reading the foundation model's features.

The released ``dinov2_vit{s,b,l,g}14_{ade20k,voc2012}_linear_head.pth`` heads are mmsegmentation ``BNHead``s
(``dinov2/eval/segmentation/models/decode_heads/linear_head.py`` in facebookresearch/dinov2) in their "linear"
configuration: the patch tokens of the backbone's *last* block after its final LayerNorm (no CLS token; the "ms"
variant, not provided here, concatenates four layers), a BatchNorm over the channels, and a 1x1 conv ``conv_seg`` to
the classes, giving logits on the token grid. Here that is ``patch.3`` (the deepest of the four exported layers,
which for the DINOv2 recipes is the last block) -> ``bn`` -> ``conv_seg``.

Output: ``classes: uint8[H, W]`` (``int16`` above 256 classes) at input resolution, the per-pixel argmax of the
logits upsampled bilinearly (``align_corners=False``, as mmsegmentation). mmsegmentation resizes in two steps
(to the network input, then to the original image) and evaluated ADE20K with sliding 512x512 windows; here the
whole frame goes through the backbone once and the logits are resized once, straight to the frame size.

Checkpoints: mmcv files, ``{"meta": ..., "state_dict": {"decode_head.bn.*", "decode_head.conv_seg.*"}}``; the
``decode_head.`` prefix is stripped and every key and shape must match (nothing is half-loaded).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import torch
from pydantic import Field
from torch import nn

from vpengine.models import palettes
from vpengine.models.base import BuildContext, Model, ModelBuildError, Options
from vpengine.models.dpt import seeded_init_
from vpengine.models.upsample_argmax import fused_unavailable, fused_upsample_argmax, upsample_argmax
from vpengine.models.weights import apply_state_dict, configured_or_default, read_state_dict, resolve_checkpoint
from vpengine.specs import TensorSpec

if TYPE_CHECKING:
    from vpengine.config import ModelConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LinearSize:
    embed_dim: int
    #: Backbone recipe the released heads were trained on (the engine warns on any other backbone).
    trained_on: str
    #: Middle of the checkpoint stem: dinov2_<arch>_<dataset>_linear_head.
    arch: str


SIZES: dict[str, LinearSize] = {
    "s": LinearSize(384, "dinov2_vits14", "vits14"),
    "b": LinearSize(768, "dinov2_vitb14", "vitb14"),
    "l": LinearSize(1024, "dinov2_vitl14", "vitl14"),
    "g": LinearSize(1536, "dinov2_vitg14", "vitg14"),
}


class LinearSegOptions(Options):
    """Options of the linear segmentation head. Recipes set ``size`` and ``dataset``; without a dataset,
    ``num_classes`` makes a custom head (class names class_0.., no released checkpoint)."""

    size: Literal["s", "b", "l", "g"] | None = Field(
        None, description="Released backbone size the head belongs to (S, B, L, g)."
    )
    dataset: Literal["ade20k", "voc2012"] | None = Field(
        None, description="Label set: ade20k (150 classes) or voc2012 (21 classes, background 0)."
    )
    num_classes: int | None = Field(
        None, ge=1, le=32767, description="Classes of a custom head; must agree with dataset if both are set."
    )
    upsample: Literal["auto", "fused", "torch"] = Field(
        "auto",
        description="How the logits become one class per pixel (Note [Fused upsample + argmax]): fused runs its "
        "Triton kernels (CUDA with Triton only; an error elsewhere), torch runs PyTorch's interpolate and argmax, "
        "auto the fused kernel where it can run and PyTorch elsewhere.",
    )


def checkpoint_name(size: str, dataset: str) -> str:
    """Catalog name (= official file stem) of a released head, e.g. ``dinov2_vits14_ade20k_linear_head``."""
    return f"dinov2_{SIZES[size].arch}_{dataset}_linear_head"


class LinearSegHead(Model):
    """DINOv2 linear head: ``patch.3: float[h*w, C]`` -> ``classes: uint8[H, W]``, per frame of a batch (recipes
    ``dinov2_linear_{ade20k,voc2012}_{s,b,l,g}``). ``state_dict`` keys: ``bn.*``, ``conv_seg.*``."""

    role = "head"
    layer = "patch.3"

    def __init__(self, ctx: BuildContext, opts: LinearSegOptions) -> None:
        super().__init__()
        where = f"{ctx.name} ({ctx.cfg.model})"
        if opts.dataset is not None:
            labels = palettes.labels(opts.dataset)
            palette = palettes.palette_bgr(opts.dataset)
            if opts.num_classes is not None and opts.num_classes != len(labels):
                raise ModelBuildError(
                    f"{where}: options.num_classes={opts.num_classes} contradicts dataset {opts.dataset!r} "
                    f"({len(labels)} classes); leave num_classes out or drop dataset"
                )
        elif opts.num_classes is not None:
            labels = [f"class_{i}" for i in range(opts.num_classes)]
            palette = _spread_palette(opts.num_classes)
        else:
            raise ModelBuildError(
                f"{where}: set options.dataset (ade20k or voc2012) or options.num_classes; got neither"
            )
        n = len(labels)
        ctx.require([self.layer])
        grid = ctx.upstream_meta.get("grid")
        if grid is None or len(grid) != 2:
            raise ModelBuildError(
                f"{where} needs the foundation model's token grid (meta 'grid' = (h, w)); the upstream meta "
                f"has: {sorted(ctx.upstream_meta)}"
            )
        self.grid = (int(grid[0]), int(grid[1]))
        spec = ctx.upstream[self.layer]
        if len(spec.shape) != 2 or spec.shape[0] != self.grid[0] * self.grid[1]:
            raise ModelBuildError(
                f"{where}: {self.layer} is {spec}, expected [{self.grid[0] * self.grid[1]}, C] for the "
                f"{self.grid[0]}x{self.grid[1]} token grid"
            )
        dim = spec.shape[1]
        self.out_hw = ctx.input_hw
        self.num_classes = n
        size = SIZES[opts.size] if opts.size is not None else None
        self.default_checkpoint = checkpoint_name(opts.size, opts.dataset) if opts.size and opts.dataset else None

        # mmseg's SyncBatchNorm (eps 1e-5) is a plain BatchNorm at inference: running statistics only.
        self.bn = nn.BatchNorm2d(dim)
        self.conv_seg = nn.Conv2d(dim, n, 1)
        self.to(ctx.dtype)

        self.input_spec = {self.layer: spec}
        self.output_spec = {"classes": TensorSpec(self.out_hw, "uint8" if n <= 256 else "int16")}
        #: "fused" or "torch": how ``forward`` upsamples (Note [Fused upsample + argmax]).
        self.upsample = "torch"
        if opts.upsample != "torch":
            # planning builds on the meta device: judge by the device the model will run on, without touching it
            device = torch.device(ctx.engine.device) if ctx.plan_only else ctx.device
            why_not = fused_unavailable(device, probe=not ctx.plan_only)
            if why_not is None:
                self.upsample = "fused"
            elif opts.upsample == "fused":
                raise ModelBuildError(
                    f"{where}: options.upsample is 'fused', which cannot run on {device}: {why_not}; use auto or torch"
                )
            elif device.type == "cuda" and not ctx.plan_only:  # on a GPU the user would expect the kernel
                log.warning("%s: PyTorch's upsampling and argmax run instead of the fused kernel: %s", where, why_not)
        self.meta = {
            "kind": "segmentation",
            "output_grid": {"classes": "labels"},  # Note [Frame grid] in engine/boundary.py
            "labels": labels,
            "palette": palette,
            "dataset": opts.dataset,
            "trained_on": size.trained_on if size and opts.dataset else None,
        }

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        return cls(ctx, ctx.options(LinearSegOptions))

    def needed_checkpoint(self, cfg: ModelConfig) -> str | None:
        return configured_or_default(cfg, self.default_checkpoint)

    def load_checkpoint(self, ctx: BuildContext) -> None:
        """Load ``decode_head.{bn,conv_seg}.*`` of an official head file strictly (all keys and shapes, or nothing)."""
        path = resolve_checkpoint(ctx, self)
        if path is None:  # weights.random_weights: the same stand-in weights in every process
            seeded_init_(self, seed=0)
            return
        sd = {k.removeprefix("decode_head."): v for k, v in read_state_dict(path).items()}
        if "bn.weight" in sd and "bn.num_batches_tracked" not in sd:
            # A training-step counter with no effect at inference; files saved without it are still complete.
            sd["bn.num_batches_tracked"] = torch.tensor(0)
        dim, n = self.conv_seg.in_channels, self.conv_seg.out_channels
        expected = f"{ctx.name} ({ctx.cfg.model}: DINOv2 linear head, {dim} channels -> {n} classes)"
        apply_state_dict(self, sd, str(path), expected, ignore=("backbone.", "auxiliary_head."))

    def logits(self, inputs: dict[str, torch.Tensor]) -> torch.Tensor:
        """Class logits on the token grid, ``[B, K, h, w]`` (before upsampling)."""
        x = inputs[self.layer].to(self.conv_seg.weight.dtype)  # [B, h*w, C]
        x = x.transpose(1, 2).reshape(x.shape[0], x.shape[-1], *self.grid)
        return self.conv_seg(self.bn(x))

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        logits = self.logits(inputs)
        dtype = self.output_spec["classes"].torch_dtype
        if self.upsample == "fused" and logits.is_cuda:
            return {"classes": fused_upsample_argmax(logits, self.out_hw, dtype)}
        return {"classes": upsample_argmax(logits, self.out_hw).to(dtype)}


def _spread_palette(n: int) -> list[list[int]]:
    """n distinct BGR colours for custom heads (golden-ratio hues), class 0 dark grey."""
    import colorsys

    out = [[60, 60, 60]]
    for i in range(1, n):
        r, g, b = colorsys.hsv_to_rgb((i * 0.618033988749895) % 1.0, 0.75, 0.95)
        out.append([round(b * 255), round(g * 255), round(r * 255)])
    return out[:n]
