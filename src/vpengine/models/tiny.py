"""Tiny random-weight models for tests, CI and the synthetic demo.

They follow exactly the interface of the real zoo (same input/output names and layouts, same preprocessing), at a
size that runs in a few milliseconds on one CPU core. Weights are seeded, so every process that builds the same
recipe gets the same weights: outputs can be recomputed in a test and compared bit for bit.

Feature naming convention, shared with DINOv2: four intermediate layers, shallow to deep, as
``patch.0 .. patch.3`` (``float[h*w, C]``, after the final norm) and ``cls.0 .. cls.3`` (``float[C]``), per frame:
like every model they run on a batch of frames at once (Note [Batched models] in base.py).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from vpengine.models.base import BuildContext, Model, Options, Pipeline
from vpengine.models.preprocess import ImagePreprocess
from vpengine.specs import TensorSpec

N_LAYERS = 4


def feature_specs(n_tokens: int, dim: int, dtype: str) -> dict[str, TensorSpec]:
    specs = {}
    for i in range(N_LAYERS):
        specs[f"patch.{i}"] = TensorSpec((n_tokens, dim), dtype)
        specs[f"cls.{i}"] = TensorSpec((dim,), dtype)
    return specs


class _Block(nn.Module):
    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.norm1 = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.norm2 = nn.LayerNorm(dim)
        self.fc1 = nn.Linear(dim, 2 * dim)
        self.fc2 = nn.Linear(2 * dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        q, k, v = self.qkv(self.norm1(x)).view(b, n, 3, self.heads, c // self.heads).permute(2, 0, 3, 1, 4)
        a = F.scaled_dot_product_attention(q, k, v).transpose(1, 2).reshape(b, n, c)
        x = x + self.proj(a)
        return x + self.fc2(F.gelu(self.fc1(self.norm2(x))))


class TinyViTOptions(Options):
    embed_dim: int = 32
    depth: int = 4
    heads: int = 2
    patch_size: int = 14
    seed: int = 0


class TinyViT(Model):
    """A 4-block ViT with DINOv2's output layout. ``image: float[3,h,w]`` -> ``patch.i``, ``cls.i``."""

    role = "foundation"
    options_type: type[TinyViTOptions] = TinyViTOptions  # a subclass may take more options

    def __init__(self, image_hw: tuple[int, int], opts: TinyViTOptions, dtype: str = "float32") -> None:
        super().__init__()
        if opts.depth < N_LAYERS:
            raise ValueError(f"tiny_vit needs depth >= {N_LAYERS}, got {opts.depth}")
        p, c = opts.patch_size, opts.embed_dim
        self.grid = (image_hw[0] // p, image_hw[1] // p)
        n = self.grid[0] * self.grid[1]
        g = torch.Generator().manual_seed(opts.seed)
        self.patch_embed = nn.Conv2d(3, c, p, p)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, c))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + n, c))
        self.blocks = nn.ModuleList(_Block(c, opts.heads) for _ in range(opts.depth))
        self.norm = nn.LayerNorm(c)
        step = opts.depth // N_LAYERS
        self.layers = [step * (i + 1) - 1 for i in range(N_LAYERS)]
        if self.patch_embed.weight.device.type != "meta":
            with torch.no_grad():
                for prm in self.parameters():
                    prm.copy_(torch.randn(prm.shape, generator=g, device="cpu") * 0.2)
        self.input_spec = {"image": TensorSpec((3, *image_hw), dtype)}
        self.output_spec = feature_specs(n, c, dtype)
        self.meta = {
            "grid": self.grid,
            "embed_dim": c,
            "patch_size": p,
            "layers": self.layers,
            "backbone": "tiny_vit",
        }

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        opts = ctx.options(cls.options_type)
        h, w = ctx.input_hw
        pre = ImagePreprocess(
            h,
            w,
            ctx.engine.foundation_model.preprocess,
            opts.patch_size,
            ctx.engine.input.color,
            ctx.engine.input.dtype,
            ctx.dtype_name,
        )
        return Pipeline(pre, cls(pre.size, opts, ctx.dtype_name))

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        x = self.patch_embed(inputs["image"]).flatten(2).transpose(1, 2)
        x = torch.cat([self.cls_token.expand(x.shape[0], -1, -1), x], 1) + self.pos_embed
        out = {}
        k = 0
        for i, blk in enumerate(self.blocks):
            x = blk(x)
            if i in self.layers:
                y = self.norm(x)
                out[f"patch.{k}"] = y[:, 1:].contiguous()
                out[f"cls.{k}"] = y[:, 0].contiguous()
                k += 1
        return out


def _seeded_(module: nn.Module, seed: int, scale: float = 0.3) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for prm in module.parameters():
            if prm.device.type != "meta":
                prm.copy_(torch.randn(prm.shape, generator=g, device="cpu") * scale)


class TinyHeadOptions(Options):
    seed: int = 1
    num_classes: int = 8
    max_detections: int = 16
    score_threshold: float = 0.5


class _TinyHead(Model):
    role = "head"
    layer = "patch.3"

    def __init__(self, ctx: BuildContext, opts: TinyHeadOptions) -> None:
        super().__init__()
        ctx.require([self.layer])
        self.grid = tuple(ctx.upstream_meta["grid"])
        self.out_hw = ctx.input_hw
        self.dim = ctx.upstream[self.layer].shape[-1]
        self.input_spec = {self.layer: ctx.upstream[self.layer]}
        self.opts = opts

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        return cls(ctx, ctx.options(TinyHeadOptions))

    def _tokens_to_map(self, t: torch.Tensor) -> torch.Tensor:  # [B, N, K] -> [B, K, gh, gw]
        return t.transpose(1, 2).reshape(t.shape[0], t.shape[-1], *self.grid).float()


class TinyDepthHead(_TinyHead):
    """``patch.3`` -> ``depth: float32[H, W]`` (positive, at input resolution)."""

    def __init__(self, ctx: BuildContext, opts: TinyHeadOptions) -> None:
        super().__init__(ctx, opts)
        self.proj = nn.Linear(self.dim, 1)
        _seeded_(self, opts.seed)
        self.output_spec = {"depth": TensorSpec(self.out_hw, "float32")}
        self.meta = {"kind": "depth", "output_grid": {"depth": "map"}}

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        m = self._tokens_to_map(self.proj(inputs[self.layer].float()))
        # softplus before the upsampling: a bilinear mix of positive values stays positive, at 1/300 of the work
        # for a 1080p output (17 ms -> 4.5 ms on one CPU core)
        d = F.interpolate(F.softplus(m), size=self.out_hw, mode="bilinear", align_corners=False)
        return {"depth": d[:, 0]}


class TinySegHead(_TinyHead):
    """``patch.3`` -> ``classes: uint8[H, W]`` (class id per pixel)."""

    def __init__(self, ctx: BuildContext, opts: TinyHeadOptions) -> None:
        super().__init__(ctx, opts)
        self.proj = nn.Linear(self.dim, opts.num_classes)
        _seeded_(self, opts.seed)
        self.output_spec = {"classes": TensorSpec(self.out_hw, "uint8")}
        self.meta = {
            "kind": "segmentation",
            "output_grid": {"classes": "labels"},
            "labels": [f"class_{i}" for i in range(opts.num_classes)],
        }

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        # argmax per token, then nearest upsampling: cheap, which is all a plumbing-test model needs
        m = self._tokens_to_map(self.proj(inputs[self.layer].float())).argmax(1, keepdim=True).float()
        return {"classes": F.interpolate(m, size=self.out_hw, mode="nearest")[:, 0].to(torch.uint8)}


class TinyDetHead(_TinyHead):
    """``patch.3`` -> fixed-capacity detections: ``boxes[M,4]`` (x1,y1,x2,y2 input pixels), ``scores``, ``labels``,
    ``count``. Every token cell whose score passes the threshold is a detection, best first, up to M."""

    def __init__(self, ctx: BuildContext, opts: TinyHeadOptions) -> None:
        super().__init__(ctx, opts)
        self.proj = nn.Linear(self.dim, 1 + opts.num_classes)
        _seeded_(self, opts.seed)
        m = opts.max_detections
        self.output_spec = {
            "boxes": TensorSpec((m, 4), "float32"),
            "scores": TensorSpec((m,), "float32"),
            "labels": TensorSpec((m,), "int32"),
            "count": TensorSpec((), "int32"),
        }
        gh, gw = self.grid
        h, w = self.out_hw
        # Computed on the CPU and then moved to where the model is built: integer arithmetic on the meta device
        # (planning) runs PyTorch's Python reference kernels, whose first use imports torch._dynamo, ~2 s of every
        # CLI start with this head.
        ys, xs = torch.meshgrid(torch.arange(gh, device="cpu"), torch.arange(gw, device="cpu"), indexing="ij")
        cells = torch.stack([xs * w / gw, ys * h / gh, (xs + 1) * w / gw, (ys + 1) * h / gh], -1).reshape(-1, 4)
        self.register_buffer("cells", cells.float().to(torch.get_default_device()), persistent=False)
        self.meta = {
            "kind": "detection",
            "output_grid": {"boxes": "boxes"},
            "labels": [f"class_{i}" for i in range(opts.num_classes)],
            "max_detections": m,
        }

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        logits = self.proj(inputs[self.layer].float())  # B, N, 1+K
        scores = torch.sigmoid(logits[..., 0])
        labels = logits[..., 1:].argmax(-1).to(torch.int32)
        b, m = scores.shape[0], self.opts.max_detections
        k = min(m, scores.shape[1])
        top, idx = scores.topk(k, dim=1)
        keep = top >= self.opts.score_threshold
        count = keep.sum(1).to(torch.int32)
        boxes = torch.zeros(b, m, 4, device=scores.device)
        out_scores = torch.zeros(b, m, device=scores.device)
        out_labels = torch.full((b, m), -1, dtype=torch.int32, device=scores.device)
        boxes[:, :k] = torch.where(keep[..., None], self.cells[idx], 0.0)
        out_scores[:, :k] = torch.where(keep, top, 0.0)
        out_labels[:, :k] = torch.where(keep, labels.gather(1, idx), -1)
        return {"boxes": boxes, "scores": out_scores, "labels": out_labels, "count": count}

    def finalize(self, outputs: dict[str, np.ndarray]) -> dict[str, Any]:
        n = int(outputs["count"])
        return {**{k: outputs[k][:n] for k in ("boxes", "scores", "labels")}, "count": n}
