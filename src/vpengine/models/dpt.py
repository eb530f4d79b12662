"""Depth-Anything-V2's DPT depth head, reading the foundation model's features.

Depth-Anything-V2 (Yang et al., 2024) is a DINOv2 backbone fine-tuned together with a DPT decoder. This module is
that decoder, ``DPTHead`` of ``depth_anything_v2/dpt.py`` in the DepthAnything/Depth-Anything-V2 repository, as a
vpengine head: it reads ``patch.0 .. patch.3`` (and ``cls.0 .. cls.3`` only with ``use_clstoken``) of a batch of
frames and produces, per frame (Note [Batched models] in base.py),

* ``depth: float32[H, W]`` at input resolution: relative *inverse* depth (disparity-like: larger is nearer, known
  up to scale and shift), exactly as the reference ``infer_image`` produces it, never quantised.
* with ``postprocess: {output: colormap | both}`` also (or only) ``depth_color: uint8[H, W, 3]``, BGR, min-max
  scaled per frame and colour-mapped on the model's device (the colours of ``vpengine.visualize.colorize_depth``).

The forward pass follows the reference step by step: per layer a 1x1 projection and a resize (4x and 2x transposed
convs, identity, a stride-2 conv), 3x3 ``layerN_rn`` convs to a common width, four fusion blocks (two pre-activation
residual units each, bilinear upsampling with ``align_corners=True``) from deep to shallow, ``output_conv1``, a
bilinear resize to the backbone's input size (token grid x patch size), ``output_conv2`` ending in a ReLU, and a
final bilinear resize (``align_corners=True``) to the frame size.

Module names equal the reference ``depth_head.*`` names, so the official ``depth_anything_v2_vit{s,b,l}.pth`` loads
strictly: ``depth_head.`` is stripped and the backbone's ``pretrained.*`` keys are ignored (the backbone loads them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import torch
import torch.nn.functional as F
from pydantic import Field, field_validator
from torch import nn

from vpengine import colormaps
from vpengine.models.base import BuildContext, Model, ModelBuildError, Options, Pipeline
from vpengine.models.weights import apply_state_dict, configured_or_default, read_state_dict, resolve_checkpoint
from vpengine.specs import TensorSpec

if TYPE_CHECKING:
    from vpengine.config import ModelConfig

N_LAYERS = 4


@dataclass(frozen=True)
class DPTSize:
    """One released Depth-Anything-V2 head: its widths, the backbone it was trained on, its checkpoint."""

    features: int
    out_channels: tuple[int, int, int, int]
    #: Backbone recipe the released weights were fine-tuned with (the engine warns on any other backbone).
    trained_on: str
    #: Catalog name of the released checkpoint (holds backbone and head).
    checkpoint: str


SIZES: dict[str, DPTSize] = {
    "s": DPTSize(64, (48, 96, 192, 384), "dinov2_vits14_dav2", "depth_anything_v2_vits"),
    "b": DPTSize(128, (96, 192, 384, 768), "dinov2_vitb14_dav2", "depth_anything_v2_vitb"),
    "l": DPTSize(256, (256, 512, 1024, 1024), "dinov2_vitl14_dav2", "depth_anything_v2_vitl"),
}


class DPTOptions(Options):
    """Options of the DPT depth head. A recipe sets ``size``; ``features``/``out_channels`` override its widths
    (a custom, e.g. tiny, head: then no released checkpoint fits it)."""

    size: Literal["s", "b", "l"] | None = Field(
        None, description="Released head size (S, B, L); null needs features and out_channels."
    )
    features: int | None = Field(None, ge=2, le=4096, description="Fusion width (S 64, B 128, L 256).")
    out_channels: tuple[int, int, int, int] | None = Field(
        None, description="Projection widths of the four layers, shallow to deep."
    )
    use_bn: bool = Field(False, description="BatchNorm in the residual units (False in every release).")
    use_clstoken: bool = Field(
        False, description="Mix the CLS token into each layer's tokens (False in every release)."
    )

    @field_validator("out_channels")
    @classmethod
    def _positive(cls, v: tuple[int, int, int, int] | None) -> tuple[int, int, int, int] | None:
        if v is not None and any(c < 1 for c in v):
            raise ValueError(f"out_channels must be 4 positive widths, got {list(v)}")
        return v


class DepthPostprocessOptions(Options):
    """``postprocess`` block of a depth head."""

    output: Literal["raw", "colormap", "both"] = Field(
        "raw",
        description="raw: depth (float32); colormap: depth_color only (uint8 BGR); both: depth and depth_color.",
    )
    cmap: str = Field(
        "Spectral_r", description="colormap of depth_color: a matplotlib name (Depth-Anything-V2 uses Spectral_r)."
    )

    @field_validator("cmap")
    @classmethod
    def _known(cls, v: str) -> str:
        colormaps.lut(v)  # ValueError naming the accepted maps
        return v


# ----------------------------------------------------------------------------------------------- building blocks
class ResidualConvUnit(nn.Module):
    """Pre-activation residual unit: ``x + conv2(relu(conv1(relu(x))))`` (BatchNorm after each conv if ``bn``)."""

    def __init__(self, features: int, bn: bool) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1, bias=True)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1, bias=True)
        self.bn1: nn.Module = nn.BatchNorm2d(features) if bn else nn.Identity()
        self.bn2: nn.Module = nn.BatchNorm2d(features) if bn else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # The reference ReLU is not in place: x itself must survive for the skip connection.
        out = self.bn1(self.conv1(F.relu(x)))
        out = self.bn2(self.conv2(F.relu(out)))
        return out + x


class FeatureFusionBlock(nn.Module):
    """RefineNet-style fusion: ``x (+ unit1(skip))`` -> ``unit2`` -> bilinear resize -> 1x1 ``out_conv``.

    The resize goes to ``size`` (the next, shallower layer's grid) or, for the last block, doubles the grid.
    ``resConfUnit1`` exists in every block, also the deepest one that never uses it, because the checkpoints hold it.
    """

    def __init__(self, features: int, bn: bool) -> None:
        super().__init__()
        self.out_conv = nn.Conv2d(features, features, 1, bias=True)
        self.resConfUnit1 = ResidualConvUnit(features, bn)
        self.resConfUnit2 = ResidualConvUnit(features, bn)

    def forward(
        self, x: torch.Tensor, skip: torch.Tensor | None = None, size: tuple[int, int] | None = None
    ) -> torch.Tensor:
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        if size is None:
            x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=True)
        else:
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=True)
        return self.out_conv(x)


class _Scratch(nn.Module):
    """Container named like the reference's ``scratch`` (so checkpoint keys match)."""

    def __init__(self, out_channels: tuple[int, int, int, int], features: int, bn: bool) -> None:
        super().__init__()
        self.layer1_rn = nn.Conv2d(out_channels[0], features, 3, padding=1, bias=False)
        self.layer2_rn = nn.Conv2d(out_channels[1], features, 3, padding=1, bias=False)
        self.layer3_rn = nn.Conv2d(out_channels[2], features, 3, padding=1, bias=False)
        self.layer4_rn = nn.Conv2d(out_channels[3], features, 3, padding=1, bias=False)
        self.refinenet1 = FeatureFusionBlock(features, bn)
        self.refinenet2 = FeatureFusionBlock(features, bn)
        self.refinenet3 = FeatureFusionBlock(features, bn)
        self.refinenet4 = FeatureFusionBlock(features, bn)
        self.output_conv1 = nn.Conv2d(features, features // 2, 3, padding=1)
        # Indices 0 and 2 carry weights: the checkpoint keys are output_conv2.0.* and output_conv2.2.*.
        self.output_conv2 = nn.Sequential(
            nn.Conv2d(features // 2, 32, 3, padding=1),
            nn.ReLU(True),
            nn.Conv2d(32, 1, 1),
            nn.ReLU(True),  # the final ReLU: depth >= 0
            nn.Identity(),
        )


# ------------------------------------------------------------------------------------------------------- head
class DPTDepthHead(Model):
    """Depth-Anything-V2 DPT head: ``patch.0..3`` (+ ``cls.0..3``) -> ``depth: float32[H, W]``.

    Build it with :meth:`from_config` (recipes ``dav2_depth_s|b|l``); its ``state_dict`` keys are the reference
    ``depth_head.*`` keys without the prefix.
    """

    role = "head"

    def __init__(self, ctx: BuildContext, opts: DPTOptions) -> None:
        super().__init__()
        size = SIZES[opts.size] if opts.size is not None else None
        features = opts.features or (size.features if size else None)
        out_channels = opts.out_channels or (size.out_channels if size else None)
        if features is None or out_channels is None:
            raise ModelBuildError(
                f"{ctx.name} ({ctx.cfg.model}): set options.size (one of {', '.join(SIZES)}) or both "
                f"options.features and options.out_channels; got size={opts.size}, features={opts.features}, "
                f"out_channels={opts.out_channels}"
            )
        custom = size is not None and (features, tuple(out_channels)) != (size.features, size.out_channels)
        self.keys = [f"patch.{i}" for i in range(N_LAYERS)]
        if opts.use_clstoken:
            self.keys += [f"cls.{i}" for i in range(N_LAYERS)]
        ctx.require(self.keys)
        self.grid, self.patch_size, dim = _upstream_geometry(ctx)
        self.out_hw = ctx.input_hw
        self.use_clstoken = opts.use_clstoken
        #: Catalog name loaded when the config names no checkpoint (None for custom widths).
        self.default_checkpoint = size.checkpoint if size and not custom else None

        self.projects = nn.ModuleList(nn.Conv2d(dim, c, 1) for c in out_channels)
        self.resize_layers = nn.ModuleList(
            [
                nn.ConvTranspose2d(out_channels[0], out_channels[0], 4, stride=4),
                nn.ConvTranspose2d(out_channels[1], out_channels[1], 2, stride=2),
                nn.Identity(),
                nn.Conv2d(out_channels[3], out_channels[3], 3, stride=2, padding=1),
            ]
        )
        if opts.use_clstoken:
            self.readout_projects = nn.ModuleList(
                nn.Sequential(nn.Linear(2 * dim, dim), nn.GELU()) for _ in range(N_LAYERS)
            )
        self.scratch = _Scratch(tuple(out_channels), features, opts.use_bn)  # type: ignore[arg-type]
        self.to(ctx.dtype)

        self.input_spec = {k: ctx.upstream[k] for k in self.keys}
        self.output_spec = {"depth": TensorSpec(self.out_hw, "float32")}
        self.meta = {
            "kind": "depth",
            "output_grid": {"depth": "map"},  # Note [Frame grid] in engine/boundary.py
            "depth_type": "relative_inverse",  # disparity-like: larger is nearer, up to scale and shift
            "trained_on": size.trained_on if size and not custom else None,
        }

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        post = ctx.postprocess_options(DepthPostprocessOptions)
        head = cls(ctx, ctx.options(DPTOptions))
        if post.output == "raw":
            return head
        return Pipeline(head, DepthColormap(head.out_hw, post.cmap, keep_depth=post.output == "both"))

    def needed_checkpoint(self, cfg: ModelConfig) -> str | None:
        return configured_or_default(cfg, self.default_checkpoint)

    def load_checkpoint(self, ctx: BuildContext) -> None:
        """Load ``depth_head.*`` of a Depth-Anything-V2 checkpoint strictly (all keys, all shapes, or nothing)."""
        path = resolve_checkpoint(ctx, self)
        if path is None:  # weights.random_weights: the same stand-in weights in every process
            seeded_init_(self, seed=0)
            # Non-negative last weights on ReLU'd features: random depth that varies instead of a map of zeros.
            with torch.no_grad():
                self.scratch.output_conv2[2].weight.abs_()
            return
        sd = {k.removeprefix("depth_head."): v for k, v in read_state_dict(path).items()}
        expected = f"{ctx.name} ({ctx.cfg.model}: Depth-Anything-V2 DPT head, {self._describe()})"
        apply_state_dict(self, sd, str(path), expected, ignore=("pretrained.",))

    def _describe(self) -> str:
        widths = [int(p.weight.shape[0]) for p in self.projects]  # type: ignore[union-attr]
        dim = int(self.projects[0].weight.shape[1])  # type: ignore[union-attr]
        feats = int(self.scratch.layer1_rn.weight.shape[0])
        return f"embed_dim {dim}, out_channels {widths}, features {feats}"

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        gh, gw = self.grid
        dtype = self.scratch.layer1_rn.weight.dtype
        layers = []
        for i in range(N_LAYERS):
            x = inputs[f"patch.{i}"].to(dtype)  # [B, gh*gw, C]
            if self.use_clstoken:
                cls_tok = inputs[f"cls.{i}"].to(dtype)[:, None].expand_as(x)
                x = self.readout_projects[i](torch.cat((x, cls_tok), -1))
            x = x.transpose(1, 2).reshape(x.shape[0], x.shape[-1], gh, gw)
            layers.append(self.resize_layers[i](self.projects[i](x)))
        s = self.scratch
        rn = (s.layer1_rn, s.layer2_rn, s.layer3_rn, s.layer4_rn)
        l1, l2, l3, l4 = (conv(x) for conv, x in zip(rn, layers))
        path = s.refinenet4(l4, size=tuple(l3.shape[2:]))
        path = s.refinenet3(path, l3, size=tuple(l2.shape[2:]))
        path = s.refinenet2(path, l2, size=tuple(l1.shape[2:]))
        path = s.refinenet1(path, l1)
        out = s.output_conv1(path)
        # The reference resizes to the backbone's input size (patch grid x 14 for its ViT-*/14 backbones).
        out = F.interpolate(out, (gh * self.patch_size, gw * self.patch_size), mode="bilinear", align_corners=True)
        # output_conv2 ends in a ReLU, so the reference's extra F.relu after the head (idempotent) is left out.
        out = s.output_conv2(out)
        if tuple(out.shape[-2:]) != self.out_hw:
            out = F.interpolate(out, self.out_hw, mode="bilinear", align_corners=True)
        return {"depth": out[:, 0].float()}


@torch.no_grad()
def seeded_init_(module: nn.Module, seed: int) -> None:
    """Re-initialise ``module`` from a seeded CPU generator: PyTorch's default ranges (uniform within
    1/sqrt(fan_in) for conv and linear layers, identity BatchNorm), but the same values on every device and in
    every process, so random-weight runs are reproducible across thread and process mode and restarts."""
    g = torch.Generator().manual_seed(seed)
    for m in module.modules():
        if isinstance(m, nn.modules.batchnorm._BatchNorm):
            m.reset_parameters()
        elif isinstance(m, (nn.Conv2d, nn.ConvTranspose2d, nn.Linear)):
            bound = 1.0 / math.sqrt(m.weight[0].numel())
            # device="cpu": a CPU generator, whatever default device a caller's context has set.
            m.weight.copy_((torch.rand(m.weight.shape, generator=g, device="cpu") * 2 - 1) * bound)
            if m.bias is not None:
                m.bias.copy_((torch.rand(m.bias.shape, generator=g, device="cpu") * 2 - 1) * bound)


def _upstream_geometry(ctx: BuildContext) -> tuple[tuple[int, int], int, int]:
    """(grid, patch size, embed dim) of the upstream features, checked against the declared specs."""
    grid = ctx.upstream_meta.get("grid")
    if grid is None or len(grid) != 2:
        raise ModelBuildError(
            f"{ctx.name} ({ctx.cfg.model}) needs the foundation model's token grid (meta 'grid' = (h, w)); "
            f"the upstream meta has: {sorted(ctx.upstream_meta)}"
        )
    gh, gw = (int(v) for v in grid)
    patch = int(ctx.upstream_meta.get("patch_size", 14))
    dims = set()
    for i in range(N_LAYERS):
        spec = ctx.upstream[f"patch.{i}"]
        if len(spec.shape) != 2 or spec.shape[0] != gh * gw:
            raise ModelBuildError(
                f"{ctx.name} ({ctx.cfg.model}): patch.{i} is {spec}, expected [{gh * gw}, C] for the "
                f"{gh}x{gw} token grid"
            )
        dims.add(spec.shape[1])
    if len(dims) != 1:
        raise ModelBuildError(f"{ctx.name} ({ctx.cfg.model}): patch.0..3 must share one width, got {sorted(dims)}")
    return (gh, gw), patch, dims.pop()


# ------------------------------------------------------------------------------------------- postprocessing
class DepthColormap(Model):
    """``depth: float32[H, W]`` -> ``depth_color: uint8[H, W, 3]`` (BGR), on the depth's device.

    Per frame min-max scaling over the finite pixels (each frame of a batch by its own minimum and maximum), then
    a 256-entry colormap lookup: the same arithmetic as ``vpengine.visualize.colorize_depth`` (non-finite pixels
    are black), without a trip through the host.
    """

    def __init__(self, hw: tuple[int, int], cmap: str = "Spectral_r", keep_depth: bool = False) -> None:
        super().__init__()
        # torch.tensor (not from_numpy) so the table lands on the device the model is being built on.
        self.register_buffer("lut", torch.tensor(colormaps.lut(cmap).tolist(), dtype=torch.uint8), persistent=False)
        self.keep_depth = keep_depth
        depth = TensorSpec(hw, "float32")
        self.input_spec = {"depth": depth}
        self.output_spec = {"depth": depth} if keep_depth else {}
        self.output_spec["depth_color"] = TensorSpec((*hw, 3), "uint8")
        self.meta = {"output_grid": dict.fromkeys(self.output_spec, "map")}

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        d = inputs["depth"].float()  # B, H, W
        finite = torch.isfinite(d)
        lo = torch.where(finite, d, torch.inf).amin(dim=(1, 2), keepdim=True)
        hi = torch.where(finite, d, -torch.inf).amax(dim=(1, 2), keepdim=True)
        scaled = (d - lo) / (hi - lo).clamp_min(1e-12)
        idx = torch.where(finite, (scaled.clamp(0, 1) * 255).round(), 0).long()
        color = self.lut[idx].masked_fill_(~finite[..., None], 0)
        out = {"depth_color": color}
        if self.keep_depth:
            out["depth"] = inputs["depth"]
        return out
