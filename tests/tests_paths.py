"""Paths used by tests."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MEDIA = ROOT.parent / "shared" / "data" / "media"
TINY = ROOT / "configs" / "tiny.yaml"


def tiny(mode: str = "process", *overrides: str):
    """The tiny config (120x160 frames, tiny_vit + depth/seg/det) with dotted overrides."""
    from vpengine.config import load_config

    return load_config(TINY, [f"mode={mode}", *overrides])
