"""Built-in recipes. Each line maps a config name to a model class (imported only when used) and its presets.

Families register in their own blocks below; keep one block per model module.
"""

from vpengine.models.registry import register

# --- tiny random-weight models: tests, CI, the synthetic demo -------------------------------------------------------
register("tiny_vit", "vpengine.models.tiny:TinyViT", "foundation", "4-block ViT/14 with DINOv2's output layout")
register("tiny_depth", "vpengine.models.tiny:TinyDepthHead", "head", "linear depth head (float32 at input size)")
register("tiny_seg", "vpengine.models.tiny:TinySegHead", "head", "linear segmentation head (class id map)")
register("tiny_det", "vpengine.models.tiny:TinyDetHead", "head", "per-cell detector with fixed capacity")

# --- DINOv2 backbones (models/dinov2.py) ---------------------------------------------------------------------------
_DINOV2 = "vpengine.models.dinov2:DinoV2"
for _size, _title in (("s", "ViT-S/14"), ("b", "ViT-B/14"), ("l", "ViT-L/14"), ("g", "ViT-G/14")):
    # Default checkpoints are catalog names equal to the official file stems (models/catalog.py).
    register(
        f"dinov2_vit{_size}14",
        _DINOV2,
        "foundation",
        f"DINOv2 {_title} (facebookresearch release)",
        size=_size,
        default_checkpoint=f"dinov2_vit{_size}14_pretrain",
    )
    register(
        f"dinov2_vit{_size}14_reg4",
        _DINOV2,
        "foundation",
        f"DINOv2 {_title} with 4 registers",
        size=_size,
        registers=4,
        default_checkpoint=f"dinov2_vit{_size}14_reg4_pretrain",
    )
    if _size != "g":  # Depth-Anything-V2's fine-tuned encoder ('pretrained.*' of depth_anything_v2_vit?.pth)
        register(
            f"dinov2_vit{_size}14_dav2",
            _DINOV2,
            "foundation",
            f"DINOv2 {_title} fine-tuned by Depth-Anything-V2",
            size=_size,
            default_checkpoint=f"depth_anything_v2_vit{_size}",
            # Depth-Anything-V2's own code resamples position embeddings the original DINOv2 way; match it so
            # depth maps equal the reference implementation's (the plain recipes match Hugging Face instead).
            pos_embed_interpolation="dinov2",
        )

# --- Depth-Anything-V2 depth heads (models/dpt.py) -----------------------------------------------------------------
for _size, _backbone in (("s", "ViT-S"), ("b", "ViT-B"), ("l", "ViT-L")):
    register(
        f"dav2_depth_{_size}",
        "vpengine.models.dpt:DPTDepthHead",
        "head",
        f"Depth-Anything-V2 {_backbone} DPT head: relative inverse depth, float32 at input size",
        size=_size,
    )

# --- DINOv2 linear segmentation heads (models/linear_seg.py) -------------------------------------------------------
for _dataset, _n in (("ade20k", 150), ("voc2012", 21)):
    for _size, _backbone in (("s", "ViT-S"), ("b", "ViT-B"), ("l", "ViT-L"), ("g", "ViT-g")):
        register(
            f"dinov2_linear_{_dataset}_{_size}",
            "vpengine.models.linear_seg:LinearSegHead",
            "head",
            f"DINOv2 {_backbone}/14 linear segmentation head, {_dataset} ({_n} classes, uint8 class ids)",
            size=_size,
            dataset=_dataset,
        )

# --- Faster R-CNN detection heads (models/detection.py) ------------------------------------------------------------
register(
    "frcnn_dinov2",
    "vpengine.models.detection:FasterRCNNHead",
    "head",
    "Faster R-CNN (ViTDet simple pyramid, torchvision RPN/RoI heads) on patch.3; train with `vpengine train detector`",
)
register(
    "frcnn_dinov2_lite",
    "vpengine.models.detection:FasterRCNNHead",
    "head",
    "frcnn_dinov2 sized for embedded GPUs: 128-channel pyramid, 512-wide box head, 300 proposals",
    out_channels=128,
    representation_size=512,
    rpn_pre_nms_top_n_test=500,
    rpn_post_nms_top_n_test=300,
)
