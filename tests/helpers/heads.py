"""One head built alone, on the features of a given token grid: the config around it (a tiny foundation model, random
weights unless a checkpoint is given) and the upstream specs a DINOv2 backbone would hand it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from vpengine.config import EngineConfig, load_config
from vpengine.models.base import Model
from vpengine.models.build import build_model
from vpengine.models.tiny import feature_specs


def head_config(
    hw: tuple[int, int], head: dict[str, Any], checkpoint: str | Path | None = None, **top: Any
) -> EngineConfig:
    """Thread mode on ``hw`` frames with ``head`` (a heads entry) as its one head; ``top``: more top-level fields."""
    head = dict(head)
    if checkpoint is not None:
        head["checkpoint"] = str(checkpoint)
    return load_config(
        {
            "mode": "thread",
            "input": {"height": hw[0], "width": hw[1]},
            "foundation_model": {"model": "tiny_vit"},
            "heads": [head],
            "weights": {"random_weights": checkpoint is None},
            **top,
        }
    )


def upstream(grid: tuple[int, int], dim: int, dtype: str = "float32") -> tuple[dict[str, Any], dict[str, Any]]:
    """The feature specs and meta of a ``dim``-wide backbone on a ``grid`` of 14-pixel tokens."""
    return feature_specs(grid[0] * grid[1], dim, dtype), {"grid": grid, "patch_size": 14, "embed_dim": dim}


def build_head(
    cfg: EngineConfig, grid: tuple[int, int], dim: int, device: str = "cpu", dtype: str = "float32"
) -> Model:
    """The config's one head, built (weights loaded) on ``device`` for ``upstream(grid, dim, dtype)``."""
    specs, meta = upstream(grid, dim, dtype)
    return build_model(cfg, cfg.heads[0].name, "head", specs, meta, torch.device(device), plan_only=False)
