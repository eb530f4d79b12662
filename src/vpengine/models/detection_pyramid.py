"""ViTDet's simple feature pyramid for a plain ViT's token map (the Faster R-CNN head's backbone side).

State-dict keys ``pyramid.<level>.*`` of the head (models/detection.py) come from the modules here.
"""

from __future__ import annotations

from collections import OrderedDict

import torch
import torch.nn.functional as F
from torch import nn

from vpengine.models.base import ModelBuildError

#: Pyramid levels by scale relative to the token grid: their state-dict names.
LEVEL_NAMES: dict[float, str] = {4.0: "up4", 2.0: "up2", 1.0: "same", 0.5: "down2"}
#: The extra level max-pooled from the coarsest one (RPN only, as in torchvision's FPN).
TOP_LEVEL = "pool"


class LayerNorm2d(nn.Module):
    """LayerNorm over the channels of an NCHW map (ViTDet's norm): independent of batch size, unlike BatchNorm,
    which matters because the head is trained on small batches of cached features."""

    def __init__(self, channels: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.layer_norm(x.permute(0, 2, 3, 1), self.weight.shape, self.weight, self.bias, self.eps)
        return x.permute(0, 3, 1, 2)


class ConvNorm(nn.Sequential):
    """Conv (no bias) + LayerNorm2d: keys ``conv.weight``, ``norm.weight``, ``norm.bias``."""

    def __init__(self, cin: int, cout: int, kernel: int) -> None:
        super().__init__(
            OrderedDict(
                conv=nn.Conv2d(cin, cout, kernel, padding=kernel // 2, bias=False),
                norm=LayerNorm2d(cout),
            )
        )


class PyramidLevel(nn.Module):
    """One level: resample the token map (``resample``), project to ``out_channels`` (``lateral``, 1x1), then
    smooth (``output``, 3x3)."""

    def __init__(self, dim: int, out_channels: int, scale: float) -> None:
        super().__init__()
        c = dim
        if scale == 4.0:
            if dim % 4:
                raise ModelBuildError(f"pyramid scale 4 needs an embed dim divisible by 4, got {dim}")
            self.resample: nn.Module = nn.Sequential(
                nn.ConvTranspose2d(dim, dim // 2, 2, stride=2),
                LayerNorm2d(dim // 2),
                nn.GELU(),
                nn.ConvTranspose2d(dim // 2, dim // 4, 2, stride=2),
            )
            c = dim // 4
        elif scale == 2.0:
            if dim % 2:
                raise ModelBuildError(f"pyramid scale 2 needs an even embed dim, got {dim}")
            self.resample = nn.ConvTranspose2d(dim, dim // 2, 2, stride=2)
            c = dim // 2
        elif scale == 1.0:
            self.resample = nn.Identity()
        else:
            # ceil_mode: an odd grid keeps its last column; pooled cell i still covers tokens 2i and 2i+1, so the
            # stride stays exactly twice the token stride.
            self.resample = nn.MaxPool2d(2, stride=2, ceil_mode=True)
        self.lateral = ConvNorm(c, out_channels, 1)
        self.output = ConvNorm(out_channels, out_channels, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.output(self.lateral(self.resample(x)))


class SimpleFeaturePyramid(nn.Module):
    """ViTDet's simple feature pyramid from one stride-``patch`` token map: ``{level name: [B, out, h_l, w_l]}``."""

    def __init__(self, dim: int, out_channels: int, scales: list[float], top_block: bool, patch: int) -> None:
        super().__init__()
        self.level_names = [LEVEL_NAMES[s] for s in scales]
        for s, name in zip(scales, self.level_names):
            self.add_module(name, PyramidLevel(dim, out_channels, s))
        self.top_block = top_block
        #: Exact stride of every level in preprocessed-image pixels (Note [Strides that are not powers of two]).
        self.strides = [patch / s for s in scales] + ([2 * patch / scales[-1]] if top_block else [])
        self.names = self.level_names + ([TOP_LEVEL] if top_block else [])

    def forward(self, x: torch.Tensor) -> OrderedDict[str, torch.Tensor]:
        out: OrderedDict[str, torch.Tensor] = OrderedDict()
        for name in self.level_names:
            out[name] = getattr(self, name)(x)
        if self.top_block:
            # kernel 1, stride 2: every other cell, ceil(n/2) of them, exactly twice the stride
            out[TOP_LEVEL] = F.max_pool2d(out[self.level_names[-1]], 1, stride=2)
        return out
