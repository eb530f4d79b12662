"""Paths and the shared test config.

``VPENGINE_TEST_DEVICE=cuda`` runs the engine tests on a GPU (how tests/integration is run on the GPU machine);
by default everything runs on the CPU.
"""

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MEDIA = ROOT.parent / "shared" / "data" / "media"
TINY = ROOT / "configs" / "tiny.yaml"
DEVICE = os.environ.get("VPENGINE_TEST_DEVICE", "cpu")


def tiny(mode: str = "process", *overrides: str):
    """The tiny config (120x160 frames, tiny_vit + depth/seg/det) with dotted overrides, on the test device."""
    from vpengine.config import load_config

    return load_config(TINY, [f"mode={mode}", f"device={DEVICE}", *overrides])
