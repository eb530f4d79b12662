"""Built-in recipes. Each line maps a config name to a model class (imported only when used) and its presets.

Families register in their own blocks below; keep one block per model module.
"""

from vpengine.models.registry import register

# --- tiny random-weight models: tests, CI, the synthetic demo -------------------------------------------------------
register(
    "tiny_vit", "vpengine.models.tiny:TinyViT", "foundation", "4-block ViT/14 with DINOv2's output layout"
)
register(
    "tiny_depth", "vpengine.models.tiny:TinyDepthHead", "head", "linear depth head (float32 at input size)"
)
register("tiny_seg", "vpengine.models.tiny:TinySegHead", "head", "linear segmentation head (class id map)")
register("tiny_det", "vpengine.models.tiny:TinyDetHead", "head", "per-cell detector with fixed capacity")

# --- DINOv2 backbones (models/dinov2.py) ---------------------------------------------------------------------------

# --- Depth-Anything-V2 depth heads (models/dpt.py) -----------------------------------------------------------------

# --- DINOv2 linear segmentation heads (models/linear_seg.py) -------------------------------------------------------

# --- Faster R-CNN detection heads (models/detection.py) ------------------------------------------------------------
