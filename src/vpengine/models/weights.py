"""Checkpoints: where they are, how they are read (never executing code), how they are applied (all or nothing).

Resolution of a model's ``checkpoint`` field:

* ``weights.random_weights: true`` -> no file; random weights, announced loudly.
* an existing path -> that file.
* a catalog name (see ``catalog.py``) -> the file in the per-user cache; if missing, downloaded from the catalog
  with progress and sha256 verification unless offline, in which case the error names the path to place it at.
* null -> the recipe's default catalog name.

Reading: ``.safetensors`` through safetensors; anything else through ``torch.load(weights_only=True)``, which refuses
pickled code. Applying: every key is checked against the model before a single tensor is copied, so a wrong file
fails with the file name, the model it was meant for and the mismatching keys, and nothing is half-loaded.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from vpengine.models.base import BuildContext, ModelBuildError

log = logging.getLogger("vpengine.weights")

_RANDOM_WARNED: set[str] = set()


class CheckpointError(ModelBuildError):
    """A checkpoint that cannot be used: missing, unreadable, truncated, or for another model."""


def cache_dir(configured: str | None = None) -> Path:
    """The checkpoint cache: config ``weights.cache_dir``, else $VPENGINE_CACHE, else $XDG_CACHE_HOME/vpengine."""
    if configured:
        return Path(configured).expanduser()
    if os.environ.get("VPENGINE_CACHE"):
        return Path(os.environ["VPENGINE_CACHE"]).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg).expanduser() / "vpengine"


def offline(configured: bool = False) -> bool:
    """Offline if the config says so or $VPENGINE_OFFLINE / $HF_HUB_OFFLINE is set to a true value."""
    env = any(
        os.environ.get(v, "").lower() in ("1", "true", "yes") for v in ("VPENGINE_OFFLINE", "HF_HUB_OFFLINE")
    )
    return configured or env


def resolve_checkpoint(ctx: BuildContext, default: str | None) -> Path | None:
    """The local file to load for this model, or None for random weights (or while planning)."""
    if ctx.plan_only:
        return None
    wcfg = ctx.engine.weights
    name = ctx.cfg.checkpoint or default
    if wcfg.random_weights:
        if ctx.name not in _RANDOM_WARNED:
            log.warning(
                "%s (%s): RANDOM WEIGHTS, outputs are meaningless (weights.random_weights is set)",
                ctx.name,
                ctx.cfg.model,
            )
            _RANDOM_WARNED.add(ctx.name)
        return None
    if name is None:
        raise CheckpointError(
            f"{ctx.name} ({ctx.cfg.model}): no checkpoint configured and the recipe has no default; set "
            "checkpoint to a file or catalog name, or weights.random_weights: true"
        )
    path = Path(name).expanduser()
    if path.is_file():
        return path
    from vpengine.models import catalog

    cache = cache_dir(wcfg.cache_dir)
    entry = catalog.find(name, cache)  # the cache may hold the user's custom entries
    if entry is None:
        raise CheckpointError(
            f"{ctx.name} ({ctx.cfg.model}): checkpoint {name!r} is neither an existing file nor a catalog name "
            f"(`vpengine weights list` shows the catalog)"
        )
    return catalog.ensure(entry, cache, offline(wcfg.offline), for_model=ctx.name)


def read_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Tensors from a checkpoint file, without executing any code. Unwraps {'state_dict'|'model': ...}."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            sd: Any = load_file(str(path), device="cpu")
        else:
            sd = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:  # truncated, corrupt, or pickled code refused by weights_only
        raise CheckpointError(f"cannot read checkpoint {str(path)!r}: {type(e).__name__}: {e}") from None
    for key in ("state_dict", "model", "module"):
        if isinstance(sd, Mapping) and key in sd and isinstance(sd[key], Mapping):
            sd = sd[key]
    if not isinstance(sd, Mapping) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise CheckpointError(f"checkpoint {str(path)!r} does not hold a state dict of tensors")
    return dict(sd)


def _preview(keys: list[str], n: int = 8) -> str:
    return ", ".join(keys[:n]) + (f", ... ({len(keys)} in all)" if len(keys) > n else "")


def apply_state_dict(
    module: nn.Module,
    sd: Mapping[str, torch.Tensor],
    source: str,
    expected: str,
    ignore: tuple[str, ...] = (),
) -> None:
    """Load ``sd`` into ``module`` strictly, checking every key and shape first (nothing is half-loaded).

    ``source`` names the file and ``expected`` the model it should be for; both appear in the error.
    ``ignore`` lists key prefixes of the checkpoint that are not part of this module (skipped silently).
    """
    own = module.state_dict()
    theirs = {k: v for k, v in sd.items() if not k.startswith(ignore)} if ignore else dict(sd)
    missing = sorted(set(own) - set(theirs))
    unexpected = sorted(set(theirs) - set(own))
    shapes = sorted(
        f"{k}: checkpoint {tuple(theirs[k].shape)} vs model {tuple(own[k].shape)}"
        for k in set(own) & set(theirs)
        if tuple(own[k].shape) != tuple(theirs[k].shape)
    )
    if missing or unexpected or shapes:
        parts = []
        if missing:
            parts.append(f"missing keys: {_preview(missing)}")
        if unexpected:
            parts.append(f"unexpected keys: {_preview(unexpected)}")
        if shapes:
            parts.append(f"shape mismatches: {_preview(shapes, 4)}")
        raise CheckpointError(f"checkpoint {source!r} does not fit {expected}: " + "; ".join(parts))
    module.load_state_dict(theirs, strict=True)
