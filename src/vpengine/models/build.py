"""Building a model of a config: the one way every caller (workers, planning, export, training, benchmarks) does it.

``build_model`` resolves the config's recipe, builds it (on the meta device with no weights while planning, else on
the given device with its checkpoint loaded) and leaves it in eval mode with gradients off.
"""

from __future__ import annotations

import threading
from typing import Any

import torch

from vpengine.config import EngineConfig
from vpengine.models.base import BuildContext, Model, Role
from vpengine.models.registry import resolve
from vpengine.specs import SpecDict, TensorSpec

#: Held while a model is constructed, and by workers while they capture CUDA graphs. Construction draws from
#: PyTorch's process-global RNG (default layer init, seeded random weights), so thread-mode workers building at once
#: would interleave their draws and get weights that differ from run to run (and from process mode); a graph capture
#: must not overlap a build whose layer init draws from the CUDA RNG that the capture has claimed (seen on an H100).
build_lock = threading.Lock()


def model_config(cfg: EngineConfig, name: str) -> Any:
    """The config block of model ``name``: ``foundation`` or a head's name."""
    return cfg.foundation_model if name == "foundation" else cfg.head(name)


def frame_spec(cfg: EngineConfig) -> SpecDict:
    """What the foundation model reads: one frame of the configured input size and dtype."""
    return {"frame": TensorSpec((cfg.input.height, cfg.input.width, 3), cfg.input.dtype)}


def build_model(
    cfg: EngineConfig,
    name: str,
    role: Role,
    upstream: SpecDict,
    upstream_meta: dict[str, Any],
    device: torch.device,
    plan_only: bool,
) -> Model:
    """Build one recipe. With ``plan_only`` it lands on the meta device with no weights (for planning)."""
    mcfg = model_config(cfg, name)
    cls, defaults = resolve(mcfg.model, role)
    ctx = BuildContext(role, name, mcfg, cfg, upstream, upstream_meta, device, plan_only, defaults)
    with build_lock, torch.device("meta" if plan_only else device):
        model = cls.from_config(ctx)
    if not plan_only:
        model.load_checkpoint(ctx)
        model.eval().requires_grad_(False)
    return model
