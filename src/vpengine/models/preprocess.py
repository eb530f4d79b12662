"""Frame preprocessing on the model's device: uint8 HWC BGR/RGB -> float -> resize to a patch multiple -> normalise.

Aspect ratio is preserved by default: the short side goes to ``size`` and the long side is scaled by the same factor
and rounded to the nearest multiple of the patch size (1920x1080 -> 924x518 for ViT-*/14, 66x37 tokens). This is
the resize Depth-Anything-V2 uses (``lower_bound`` with ``ensure_multiple_of=14``). ``square`` reproduces the
paper's 518x518 setting, which squashes wide frames.
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections.abc import Iterator

import torch
import torch.nn.functional as F

from vpengine.config import PreprocessConfig
from vpengine.models.base import Model
from vpengine.specs import TensorSpec


def target_size(height: int, width: int, cfg: PreprocessConfig, patch: int) -> tuple[int, int]:
    """The (h, w) the model sees for a ``height`` x ``width`` frame."""
    if cfg.resize == "square":
        side = max(patch, round(cfg.size / patch) * patch)
        return side, side
    if cfg.resize == "none":
        h, w = height // patch * patch, width // patch * patch
        if h == 0 or w == 0:
            raise ValueError(f"frame {height}x{width} is smaller than one {patch}x{patch} patch")
        return h, w
    scale = cfg.size / min(height, width)

    def fit(x: float) -> int:
        y = round(x / patch) * patch
        if y < cfg.size and x >= cfg.size:  # never round the short side below the target
            y = math.ceil(x / patch) * patch
        return max(patch, int(y))

    return fit(height * scale), fit(width * scale)


#: Normalisation of every backbone in the zoo (DINOv2 and Depth-Anything-V2 were trained with ImageNet's), RGB 0..1.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

_exact = threading.local()


@contextlib.contextmanager
def exact_preprocessing() -> Iterator[None]:
    """Within the block, preprocessing takes the exact float path even on the CPU (ONNX export and its
    verification use this, because ONNX Runtime's 8-bit antialiased resize rounds differently from PyTorch's)."""
    prev = getattr(_exact, "on", False)
    _exact.on = True
    try:
        yield
    finally:
        _exact.on = prev


class ImagePreprocess(Model):
    """``frame: uint8[H, W, 3]`` (or float32 0..1) -> ``image: float[3, h, w]`` normalised, in model dtype; run on a
    batch of frames at once (Note [Batched models] in base.py)."""

    def __init__(
        self,
        height: int,
        width: int,
        cfg: PreprocessConfig,
        patch: int,
        color: str = "bgr",
        in_dtype: str = "uint8",
        dtype: str = "float32",
        mean: tuple[float, float, float] = IMAGENET_MEAN,
        std: tuple[float, float, float] = IMAGENET_STD,
    ) -> None:
        super().__init__()
        self.cfg = cfg
        self.size = target_size(height, width, cfg, patch)
        self.bgr = color == "bgr"
        self.scale = 1.0 / 255.0 if in_dtype == "uint8" else 1.0
        self.input_spec = {"frame": TensorSpec((height, width, 3), in_dtype)}
        self.output_spec = {"image": TensorSpec((3, *self.size), dtype)}
        self.out_dtype = self.output_spec["image"].torch_dtype
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32).view(1, 3, 1, 1), persistent=False)
        # normalise_mean: what the boundary pads frames with, zero once normalised (Note [Frame grid])
        self.meta = {
            "image_size": self.size,
            "input_size": (height, width),
            "patch_size": patch,
            "normalize_mean": tuple(mean),
        }

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        frame = inputs["frame"]  # B, H, W, 3
        h, w = self.size
        x = frame.permute(0, 3, 1, 2)  # B, 3, H, W: a view
        if (
            frame.device.type == "cpu"
            and frame.dtype == torch.uint8
            and self.cfg.resize != "none"
            and (frame.shape[1], frame.shape[2]) != (h, w)
            and not getattr(_exact, "on", False)
            and not torch.onnx.is_in_onnx_export()
        ):
            # On the CPU, shrink the 8-bit frame first: PyTorch's uint8 antialiased resize is ~40x faster than
            # converting a 1080p frame to float and resizing that (1 ms vs 43 ms), and differs by under one grey
            # level. GPUs take the float path below, which matches the reference implementations exactly.
            x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
            x = x.float()
            if self.bgr:
                x = x.flip(1)
            x = (x * self.scale - self.mean) / self.std
            return {"image": x.to(self.out_dtype).contiguous()}
        x = x.float()
        if self.bgr:
            x = x.flip(1)
        x = x * self.scale
        if (x.shape[-2], x.shape[-1]) != (h, w):
            if self.cfg.resize == "none":
                x = x[..., :h, :w]
            else:
                # antialias: a 1080p frame shrinks ~2x, and without it thin structures alias.
                x = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
        x = (x - self.mean) / self.std
        return {"image": x.to(self.out_dtype).contiguous()}
