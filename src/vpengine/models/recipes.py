"""Built-in recipes. Each line maps a config name to a model class (imported only when used) and its presets."""

from vpengine.models.registry import register

# Tiny random-weight models: tests, CI, the synthetic demo.
register(
    "tiny_vit", "vpengine.models.tiny:TinyViT", "foundation", "4-block ViT/14 with DINOv2's output layout"
)
register(
    "tiny_depth", "vpengine.models.tiny:TinyDepthHead", "head", "linear depth head (float32 at input size)"
)
register("tiny_seg", "vpengine.models.tiny:TinySegHead", "head", "linear segmentation head (class id map)")
register("tiny_det", "vpengine.models.tiny:TinyDetHead", "head", "per-cell detector with fixed capacity")
