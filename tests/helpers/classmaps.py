"""Reference class maps: the float64 argmax of bilinearly upsampled logits, and the check that a class map is that
argmax up to rounding at near-ties (Note [Fused upsample + argmax])."""

from __future__ import annotations

import torch
import torch.nn.functional as F


def reference(logits: torch.Tensor, size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """float64 upsampled logits ``[K, H, W]`` of ``logits: [1, K, h, w]``, and their argmax."""
    up = F.interpolate(logits.double(), size=size, mode="bilinear", align_corners=False)[0]
    return up, up.argmax(0)


def assert_argmax_of(
    got: torch.Tensor, up: torch.Tensor, best: torch.Tensor, tol: float = 1e-5, at_most: float = 1e-3
) -> float:
    """``got`` is ``best`` except where its class is within ``tol`` of the best one (a near-tie that rounding may
    flip), on at most ``at_most`` of the pixels. Returns the share of pixels that differ."""
    assert got.shape == best.shape, (got.shape, best.shape)
    wrong = got.long() != best
    share = wrong.float().mean().item()
    if wrong.any():
        chosen = up.gather(0, got.long()[None])[0]
        margin = (up.max(0).values - chosen)[wrong].max().item()
        assert margin <= tol, f"{int(wrong.sum())} pixels differ, one by {margin:.3g} (tolerance {tol:g})"
    assert share <= at_most, f"{share:.4%} of pixels differ (at most {at_most:.4%})"
    return share
