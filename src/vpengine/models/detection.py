"""Faster R-CNN object detection on the foundation model's features (no image backbone of its own).

The head reads one token layer (``patch.3`` by default: ``float[h*w, C]`` at stride 14), turns it into a small
feature pyramid the way ViTDet does for a plain ViT (transposed convolutions up, identity, max-pooling down, then a
1x1 and a 3x3 projection per level), and runs torchvision's detection parts on it: ``AnchorGenerator`` + ``RPNHead``
+ ``RegionProposalNetwork`` for proposals, ``MultiScaleRoIAlign`` + ``TwoMLPHead`` + ``FastRCNNPredictor`` inside
``RoIHeads`` for classification, box decoding and per-class NMS.

Inference (``forward``) runs those modules' layers through a path with static shapes and no host sync
(Note [Static detection] in detection_static.py), one CUDA graph per batch size under the compile backend; it gives
the detections torchvision's RPN and RoIHeads give (``predict``, ``forward_reference``), which training, ONNX export
and the tests use.

There is no ``GeneralizedRCNNTransform``: the engine already resized and normalised the frame for the foundation
model. The head knows that preprocessed size (``upstream_meta["image_size"]``) and the input frame size
(``ctx.input_hw``), works in preprocessed-image pixels inside, and maps boxes back to input-frame pixels on the way
out (see :meth:`FasterRCNNHead.boxes_to_input`).

Outputs are fixed-capacity so they fit preallocated mailbox slots (M = ``max_detections``), per frame of a batch
(Note [Batched models] in base.py: everything runs on the whole batch at once, but proposals, RoIs and NMS are per
frame, so a frame's detections never depend on the other frames)::

    boxes  float32[M, 4]   x1, y1, x2, y2 in input-frame pixels, best first; 0 past ``count``
    scores float32[M]      0 past ``count``
    labels int32[M]        index into meta["labels"]; -1 past ``count``
    count  int32[]         detections that passed score threshold and NMS (<= M)

Detections narrower or shorter than ``min_size`` input pixels (slivers clipped at the frame border) are dropped.

Note [Geometry in float32]: the learned layers (pyramid, RPN head, box head) run at the engine's precision, but
everything that handles coordinates stays float32 whatever it is: anchors, the RPN and box-predictor outputs that
are decoded into boxes, RoIAlign sampling (torchvision runs it in float32 under autocast), NMS and the mapping to
input pixels. fp16 has a 0.5-pixel spacing from 512 to 1024 and 1 pixel beyond; boxes must not snap to that grid.

Weights: no public checkpoint exists for this head; train one with ``vpengine train detector``. The state dict uses
torchvision's Faster R-CNN key layout for the parts torchvision defines (``rpn.head.*``, ``roi_heads.box_head.*``,
``roi_heads.box_predictor.*``) and ``pyramid.<level>.*`` for the feature pyramid (levels ``up4``, ``up2``, ``same``,
``down2``; the extra ``pool`` level has no weights).

Note [Strides that are not powers of two]: torchvision infers each level's stride from ``image // feature`` and
rounds RoIAlign scales to powers of two, both of which are wrong for a stride-14 ViT (1/14 would become 1/16: RoIs
sampled 12.5% off towards the origin). The head therefore sets the exact strides itself: anchors are laid out at
``14 / scale`` pixels (and centred on their token, not on its corner), RoIAlign samples at ``scale / 14``, and the
FPN level assignment counts in units where the ``same`` level is level 4, with the canonical box size scaled by
14/16 so a 196-pixel box lands on it just as a 224-pixel box lands on stride 16 in a ResNet FPN.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import Any

import numpy as np
import torch
from pydantic import Field, model_validator
from torch import nn
from torchvision.models.detection.anchor_utils import AnchorGenerator
from torchvision.models.detection.faster_rcnn import FastRCNNPredictor, TwoMLPHead
from torchvision.models.detection.image_list import ImageList
from torchvision.models.detection.roi_heads import RoIHeads
from torchvision.models.detection.rpn import RegionProposalNetwork, RPNHead
from torchvision.ops import MultiScaleRoIAlign
from torchvision.ops.poolers import initLevelMapper

from vpengine.models import detection_static
from vpengine.models.base import BuildContext, Model, ModelBuildError, Options
from vpengine.models.detection_pyramid import LEVEL_NAMES, LayerNorm2d, SimpleFeaturePyramid
from vpengine.models.weights import apply_state_dict, configured_or_default, read_state_dict, resolve_checkpoint
from vpengine.specs import TensorSpec


class FasterRCNNOptions(Options):
    """Options of the Faster R-CNN head. Sizes are in preprocessed-image pixels unless said otherwise."""

    layer: str = Field("patch.3", description="Feature the head reads (float[h*w, C]).")
    num_classes: int | None = Field(
        None, ge=1, le=10000, description="Object classes (background excluded); or give class_names."
    )
    class_names: list[str] | None = Field(
        None, description="One name per class; label i of the output is class_names[i]."
    )
    score_threshold: float = Field(0.5, ge=0.0, le=1.0, description="Keep detections whose class score is above this.")
    nms_threshold: float = Field(0.5, gt=0.0, le=1.0, description="Per-class NMS IoU threshold (1.0: no suppression).")
    max_detections: int = Field(
        100, ge=1, le=10000, description="Output capacity M: at most this many detections per frame."
    )
    min_size: float = Field(
        1.0,
        ge=0.0,
        description="Drop detections narrower or shorter than this many input pixels (slivers left by clipping).",
    )
    scales: list[float] = Field(
        [2.0, 1.0, 0.5],
        description="Pyramid levels relative to the token grid, from {4, 2, 1, 0.5}, finest first, each half the "
        "previous (stride 14/scale pixels).",
    )
    top_block: bool = Field(True, description="Add a level max-pooled from the coarsest one (RPN only).")
    out_channels: int = Field(256, ge=8, le=4096, description="Channels of every pyramid level.")
    representation_size: int = Field(1024, ge=8, le=16384, description="Width of the two-layer MLP box head.")
    roi_output_size: int = Field(7, ge=1, le=32, description="RoIAlign output side.")
    sampling_ratio: int = Field(2, ge=0, le=16, description="RoIAlign sampling points per bin (0: adaptive).")
    rpn_anchor_sizes: list[list[float]] | None = Field(
        None,
        description="Anchor sizes per pyramid level (top level included), same count on every level; null: "
        "4 and 4*sqrt(2) times each level's stride.",
    )
    rpn_aspect_ratios: list[float] = Field([0.5, 1.0, 2.0], description="Anchor height/width ratios (every level).")
    rpn_pre_nms_top_n_train: int = Field(2000, ge=1, description="Proposals per level before NMS, training.")
    rpn_pre_nms_top_n_test: int = Field(1000, ge=1, description="Proposals per level before NMS, inference.")
    rpn_post_nms_top_n_train: int = Field(2000, ge=1, description="Proposals kept after NMS, training.")
    rpn_post_nms_top_n_test: int = Field(1000, ge=1, description="Proposals kept after NMS, inference.")
    rpn_nms_threshold: float = Field(0.7, gt=0.0, le=1.0, description="Proposal NMS IoU threshold.")
    rpn_score_threshold: float = Field(0.0, ge=0.0, le=1.0, description="Drop proposals below this objectness.")
    rpn_fg_iou_threshold: float = Field(0.7, gt=0.0, le=1.0, description="Anchor IoU for a positive (training).")
    rpn_bg_iou_threshold: float = Field(0.3, ge=0.0, lt=1.0, description="Anchor IoU for a negative (training).")
    rpn_batch_size_per_image: int = Field(256, ge=1, description="Anchors sampled per image for the RPN loss.")
    rpn_positive_fraction: float = Field(0.5, gt=0.0, le=1.0, description="Positive share of those anchors.")
    box_fg_iou_threshold: float = Field(0.5, gt=0.0, le=1.0, description="Proposal IoU for a positive (training).")
    box_bg_iou_threshold: float = Field(0.5, ge=0.0, le=1.0, description="Proposal IoU below which: background.")
    box_batch_size_per_image: int = Field(512, ge=1, description="Proposals sampled per image for the box loss.")
    box_positive_fraction: float = Field(0.25, gt=0.0, le=1.0, description="Positive share of those proposals.")
    trained_on: str | None = Field(
        None, description="Backbone recipe the weights were trained on (the engine warns on a mismatch)."
    )
    seed: int = Field(0, description="Seed of the random initial weights (same weights in every process).")

    @model_validator(mode="after")
    def _check(self) -> FasterRCNNOptions:
        if self.num_classes is None and self.class_names is None:
            raise ValueError(
                "set num_classes or class_names (no public weights exist for this head, so the classes are "
                "whatever you trained it on: `vpengine train detector` writes both)"
            )
        if self.class_names is not None:
            if self.num_classes is not None and self.num_classes != len(self.class_names):
                raise ValueError(f"num_classes is {self.num_classes} but class_names has {len(self.class_names)} names")
            if not self.class_names:
                raise ValueError("class_names is empty; give at least one class")
        bad = [s for s in self.scales if s not in LEVEL_NAMES]
        if bad or not self.scales:
            raise ValueError(f"scales {self.scales} must be a non-empty list from {sorted(LEVEL_NAMES)}")
        if any(b != a / 2 for a, b in zip(self.scales, self.scales[1:])):
            raise ValueError(
                f"scales {self.scales} must go from fine to coarse, each half the previous (e.g. [2.0, 1.0, 0.5])"
            )
        if not self.rpn_aspect_ratios or any(r <= 0 for r in self.rpn_aspect_ratios):
            raise ValueError(f"rpn_aspect_ratios {self.rpn_aspect_ratios} must be positive numbers")
        return self

    @property
    def classes(self) -> list[str]:
        if self.class_names is not None:
            return list(self.class_names)
        assert self.num_classes is not None
        return [f"class_{i}" for i in range(self.num_classes)]


class ExactStrideAnchors(AnchorGenerator):
    """torchvision's anchors, laid out at the pyramid's exact strides and centred on each feature cell.

    torchvision derives strides as ``image_size // feature_size`` and puts anchor centres on cell corners; with a
    stride-14 ViT both are off (Note [Strides that are not powers of two])."""

    def __init__(
        self,
        sizes: tuple[tuple[float, ...], ...],
        aspect_ratios: tuple[tuple[float, ...], ...],
        strides: list[float],
    ) -> None:
        super().__init__(sizes, aspect_ratios)
        self.strides = list(strides)
        # The grid is fixed for a built head, so the anchors are computed once per device and dtype, not per frame.
        self._cache: dict[tuple[Any, ...], torch.Tensor] = {}

    def forward(self, image_list: ImageList, feature_maps: list[torch.Tensor]) -> list[torch.Tensor]:
        if len(feature_maps) != len(self.strides):
            raise ValueError(f"{len(feature_maps)} feature maps but anchors for {len(self.strides)} levels")
        dtype, device = torch.float32, feature_maps[0].device  # Note [Geometry in float32]
        grid_sizes = [list(f.shape[-2:]) for f in feature_maps]
        key = (dtype, device, *(tuple(g) for g in grid_sizes))
        anchors = self._cache.get(key)
        if anchors is None:
            strides = [[torch.tensor(s, dtype=dtype, device=device)] * 2 for s in self.strides]
            self.set_cell_anchors(dtype, device)
            levels = self.grid_anchors(grid_sizes, strides)
            anchors = self._cache[key] = torch.cat([a + s / 2 for a, s in zip(levels, self.strides)])
        return [anchors for _ in image_list.image_sizes]


class FloatRPNHead(RPNHead):
    """torchvision's RPN head (same weights and keys) whose outputs are float32 whatever the compute dtype.

    torchvision decodes boxes in the dtype of the predicted deltas (``BoxCoder.decode`` casts the anchors to it),
    so fp16 deltas would put every proposal on a 0.5-pixel grid past 512 pixels. See Note [Geometry in float32].
    """

    def forward(self, x: list[torch.Tensor]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        logits, deltas = super().forward(x)
        return [t.float() for t in logits], [t.float() for t in deltas]


class FloatPredictor(FastRCNNPredictor):
    """torchvision's box predictor (same weights and keys) with float32 outputs (Note [Geometry in float32])."""

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        scores, deltas = super().forward(x)
        return scores.float(), deltas.float()


def _init_weights_(head: nn.Module, seed: int) -> None:
    """Re-draw every weight from a private generator seeded with ``seed``, with the usual schemes.

    Why not seed the global RNG around construction: in thread mode other models are built at the same time in
    other threads and draw from that same global generator, so the draws would interleave and two engines (or
    thread and process mode) would start from different random weights. Schemes: torchvision's for the RPN head
    (normal, std 0.01, zero bias), PyTorch's defaults for every other conv and linear layer, identity norms.
    """
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, m in head.named_modules():
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d, nn.Linear)):
                if name.startswith("rpn.head."):
                    nn.init.normal_(m.weight, std=0.01, generator=g)
                    if m.bias is not None:
                        nn.init.zeros_(m.bias)
                    continue
                nn.init.kaiming_uniform_(m.weight, a=math.sqrt(5), generator=g)
                if m.bias is not None:
                    # weight[0].numel() is the fan-in as PyTorch's reset_parameters computes it, for all three
                    bound = 1 / math.sqrt(m.weight[0].numel())
                    nn.init.uniform_(m.bias, -bound, bound, generator=g)
            elif isinstance(m, LayerNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)


def input_box_scale(ctx: BuildContext, image_hw: tuple[int, int]) -> tuple[float, float]:
    """(sx, sy): input-frame pixels per preprocessed-image pixel, from how the engine preprocesses frames.

    ``aspect`` and ``square`` resize the whole frame, so a preprocessed pixel spans input/image pixels; ``none``
    crops the top-left patch multiple without resizing, so coordinates are the same in both."""
    h, w = ctx.input_hw
    ih, iw = image_hw
    if ctx.engine.foundation_model.preprocess.resize == "none":
        return 1.0, 1.0
    return w / iw, h / ih


class _EagerRoIAlign(MultiScaleRoIAlign):
    """Note [RoIAlign runs eagerly]: on the torchvision path (``predict``), under torch.compile, RoIAlign would be specialised for every pyramid level's
    feature size times every batch size and number of boxes it meets, and the boxes' number depends on the frame: new
    combinations keep coming after warm-up, each a recompilation of hundreds of milliseconds in the middle of a stream
    until dynamo's recompile limit is hit (seen with four cameras on an H100). It is one kernel per level either way,
    so compiling it gains nothing: it always runs as the plain torchvision op, a graph break (which that path's
    data-dependent NMS needs anyway). The static path (``forward``) pools a fixed number of boxes and compiles whole."""

    @torch.compiler.disable
    def forward(self, *args: Any, **kwargs: Any) -> torch.Tensor:
        return super().forward(*args, **kwargs)


class FasterRCNNHead(Model):
    """Faster R-CNN on ``patch.3``: fixed-capacity detections in input-frame pixels (see the module docstring)."""

    role = "head"
    # An export traces forward_reference: torchvision's RPN and RoIHeads run NMS on a data-dependent number of boxes,
    # which torch.export cannot guard on (GuardOnDataDependentSymNode); the tracing exporter records those ops as they
    # are, and ONNX has its own NMS op where it has none for vpengine::greedy_nms.
    onnx_exporter = "torchscript"

    def __init__(self, ctx: BuildContext, opts: FasterRCNNOptions) -> None:
        super().__init__()
        ctx.require([opts.layer])
        meta = ctx.upstream_meta
        if "grid" not in meta:
            raise ModelBuildError(
                f"{ctx.name} ({ctx.cfg.model}) needs the foundation model's token grid (meta 'grid'); "
                f"{ctx.engine.foundation_model.model!r} does not report one"
            )
        self.opts = opts
        self.layer = opts.layer
        self.grid = (int(meta["grid"][0]), int(meta["grid"][1]))
        spec = ctx.upstream[opts.layer]
        if len(spec.shape) != 2 or spec.shape[0] != self.grid[0] * self.grid[1]:
            raise ModelBuildError(
                f"{ctx.name} ({ctx.cfg.model}) reads {opts.layer!r} as [h*w, C] with grid {self.grid}, but it is {spec}"
            )
        self.dim = spec.shape[1]
        patch = int(meta.get("patch_size", 14))
        gh, gw = self.grid
        ih, iw = meta.get("image_size") or (gh * patch, gw * patch)
        self.image_hw = (int(ih), int(iw))
        self.input_hw = ctx.input_hw
        self.class_names = opts.classes
        k = len(self.class_names)

        # Pyramid -> RPN -> RoI heads. Attribute names give torchvision's state-dict layout (rpn.head.*,
        # roi_heads.box_head.*, roi_heads.box_predictor.*) plus pyramid.<level>.*.
        self.pyramid = SimpleFeaturePyramid(self.dim, opts.out_channels, opts.scales, opts.top_block, patch)
        strides = self.pyramid.strides
        if opts.rpn_anchor_sizes is None:
            sizes = tuple((round(4 * s), round(4 * math.sqrt(2) * s)) for s in strides)
        else:
            sizes = tuple(tuple(level) for level in opts.rpn_anchor_sizes)
            if len(sizes) != len(strides) or len({len(s) for s in sizes}) != 1 or not sizes[0]:
                raise ModelBuildError(
                    f"{ctx.name}: rpn_anchor_sizes needs one non-empty list per pyramid level "
                    f"({len(strides)}: {self.pyramid.names}), all the same length; got {opts.rpn_anchor_sizes}"
                )
        ratios = (tuple(opts.rpn_aspect_ratios),) * len(strides)
        anchors = ExactStrideAnchors(sizes, ratios, strides)
        self.rpn = RegionProposalNetwork(
            anchors,
            FloatRPNHead(opts.out_channels, anchors.num_anchors_per_location()[0]),
            fg_iou_thresh=opts.rpn_fg_iou_threshold,
            bg_iou_thresh=opts.rpn_bg_iou_threshold,
            batch_size_per_image=opts.rpn_batch_size_per_image,
            positive_fraction=opts.rpn_positive_fraction,
            pre_nms_top_n={"training": opts.rpn_pre_nms_top_n_train, "testing": opts.rpn_pre_nms_top_n_test},
            post_nms_top_n={
                "training": opts.rpn_post_nms_top_n_train,
                "testing": opts.rpn_post_nms_top_n_test,
            },
            nms_thresh=opts.rpn_nms_threshold,
            score_thresh=opts.rpn_score_threshold,
        )
        # Level assignment in "stride 16" units (Note [Strides that are not powers of two]).
        canonical_scale = round(224 * patch / 16)
        pooler = _EagerRoIAlign(
            self.pyramid.level_names,
            opts.roi_output_size,
            opts.sampling_ratio,
            canonical_scale=canonical_scale,
            canonical_level=4,
        )
        pooler.scales = [s / patch for s in opts.scales]
        k_min, k_max = (4 - int(math.log2(s)) for s in (opts.scales[0], opts.scales[-1]))
        pooler.map_levels = initLevelMapper(k_min, k_max, canonical_scale=canonical_scale, canonical_level=4)
        self.roi_heads = RoIHeads(
            pooler,
            TwoMLPHead(opts.out_channels * opts.roi_output_size**2, opts.representation_size),
            FloatPredictor(opts.representation_size, k + 1),  # + background, torchvision's label 0
            fg_iou_thresh=opts.box_fg_iou_threshold,
            bg_iou_thresh=opts.box_bg_iou_threshold,
            batch_size_per_image=opts.box_batch_size_per_image,
            positive_fraction=opts.box_positive_fraction,
            bbox_reg_weights=None,
            score_thresh=opts.score_threshold,
            nms_thresh=opts.nms_threshold,
            detections_per_img=opts.max_detections,
        )

        # Python floats, not buffers: a backend casting the head to fp16 would round 160/112 to 1.429 (a pixel off
        # at the right edge of a 1080p frame). Note [Geometry in float32].
        self.box_scale = input_box_scale(ctx, self.image_hw)

        m = opts.max_detections
        self.input_spec = {opts.layer: spec}
        self.output_spec = {
            "boxes": TensorSpec((m, 4), "float32"),
            "scores": TensorSpec((m,), "float32"),
            "labels": TensorSpec((m,), "int32"),
            "count": TensorSpec((), "int32"),
        }
        self.meta = {
            "kind": "detection",
            "output_grid": {"boxes": "boxes"},  # Note [Frame grid] in engine/boundary.py
            "labels": self.class_names,
            "max_detections": m,
            "layer": opts.layer,
            "pyramid": dict(zip(self.pyramid.names, strides)),
        }
        if opts.trained_on:
            self.meta["trained_on"] = opts.trained_on

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        opts = ctx.options(FasterRCNNOptions)
        if ctx.plan_only:
            return cls(ctx, opts)
        # Built and initialised on the CPU, then moved: see _init_weights_.
        with torch.device("cpu"):
            head = cls(ctx, opts)
        _init_weights_(head, opts.seed)
        return head.to(ctx.device)

    def needed_checkpoint(self, cfg: Any) -> str | None:
        return configured_or_default(cfg, None)  # no default catalog entry: a file, or random weights

    def load_checkpoint(self, ctx: BuildContext) -> None:
        """Load ``checkpoint`` strictly (there is no default catalog entry: a file, or random weights)."""
        path = resolve_checkpoint(ctx, self)
        if path is None:
            return
        sd = read_state_dict(path)
        # torchvision < 0.11 saved the RPN conv without its Conv2dNormActivation wrapper
        for suffix in ("weight", "bias"):
            old = f"rpn.head.conv.{suffix}"
            if old in sd:
                sd[f"rpn.head.conv.0.0.{suffix}"] = sd.pop(old)
        apply_state_dict(self, sd, str(path), f"{ctx.name} ({ctx.cfg.model}, {self.describe()})")

    def describe(self) -> str:
        o = self.opts
        return (
            f"{len(self.class_names)} classes, embed dim {self.dim}, out_channels {o.out_channels}, "
            f"representation_size {o.representation_size}, scales {o.scales}"
        )

    # ------------------------------------------------------------------------------------------ coordinates
    def boxes_to_input(self, boxes: torch.Tensor) -> torch.Tensor:
        """Preprocessed-image pixels -> input-frame pixels (x1, y1, x2, y2, float32), clipped to the frame."""
        (sx, sy), (h, w) = self.box_scale, self.input_hw
        b = boxes.float()
        x = (b[:, 0::2] * sx).clamp(0, w)
        y = (b[:, 1::2] * sy).clamp(0, h)
        return torch.stack([x[:, 0], y[:, 0], x[:, 1], y[:, 1]], 1)

    def boxes_to_image(self, boxes: torch.Tensor) -> torch.Tensor:
        """Input-frame pixels -> preprocessed-image pixels (the inverse of :meth:`boxes_to_input`)."""
        sx, sy = self.box_scale
        b = boxes.float()
        return torch.stack([b[:, 0] / sx, b[:, 1] / sy, b[:, 2] / sx, b[:, 3] / sy], 1)

    # ------------------------------------------------------------------------------------------ running
    def feature_maps(self, tokens: torch.Tensor) -> OrderedDict[str, torch.Tensor]:
        """``tokens: [B, h*w, C]`` -> the pyramid ``{level: [B, out_channels, h_l, w_l]}``."""
        b, _, c = tokens.shape
        # the weights' dtype: float32, or the precision a backend cast the head to
        dtype = self.roi_heads.box_head.fc6.weight.dtype
        x = tokens.to(dtype).transpose(1, 2).reshape(b, c, *self.grid)
        return self.pyramid(x)

    def _images(self, batch: int, device: torch.device) -> ImageList:
        # The RPN and RoI heads only read image_sizes (clipping, anchors are ours): a 0-channel placeholder
        # stands in for the image tensor and allocates nothing.
        h, w = self.image_hw
        return ImageList(torch.empty(batch, 0, h, w, device=device), [(h, w)] * batch)

    def predict(
        self, tokens: torch.Tensor, proposals: list[torch.Tensor] | None = None
    ) -> list[dict[str, torch.Tensor]]:
        """Detections for a batch of token maps, each ``{"boxes", "scores", "labels"}`` of variable length.

        Boxes are in input-frame pixels, best first; labels index :attr:`class_names`. ``proposals`` (one
        ``[N, 4]`` tensor per image, preprocessed-image pixels) replaces the RPN, for evaluation and tests.
        Needs eval mode.
        """
        if self.training:
            raise RuntimeError("predict() runs in eval mode; call .eval() first (training uses losses())")
        maps = self.feature_maps(tokens)
        images = self._images(tokens.shape[0], tokens.device)
        if proposals is None:
            proposals, _ = self.rpn(images, maps)
        dets, _ = self.roi_heads(maps, proposals, images.image_sizes)
        out = []
        for d in dets:
            boxes = self.boxes_to_input(d["boxes"])
            # RoIHeads drops only boxes under 0.01 preprocessed pixels; a box clipped to a sliver along the frame
            # border survives that and is no use to anyone downstream.
            keep = ((boxes[:, 2:] - boxes[:, :2]) >= self.opts.min_size).all(1)
            out.append({"boxes": boxes[keep], "scores": d["scores"][keep], "labels": d["labels"][keep] - 1})
        return out

    def losses(self, tokens: torch.Tensor, targets: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
        """Training losses (RPN objectness and box, classifier, box regression) for a batch of token maps.

        ``targets[i]``: ``boxes`` float[n, 4] in input-frame pixels and ``labels`` int64[n] indexing
        :attr:`class_names` (the same conventions as the outputs). Needs train mode.
        """
        if not self.training:
            raise RuntimeError("losses() runs in train mode; call .train() first")
        if len(targets) != tokens.shape[0]:
            raise ValueError(f"{tokens.shape[0]} token maps but {len(targets)} targets")
        k = len(self.class_names)
        tv_targets = []
        for i, t in enumerate(targets):
            labels = t["labels"].to(torch.int64)
            if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) >= k):
                raise ValueError(f"target {i}: labels {labels.tolist()} outside 0..{k - 1}")
            tv_targets.append({"boxes": self.boxes_to_image(t["boxes"].float()).reshape(-1, 4), "labels": labels + 1})
        maps = self.feature_maps(tokens)
        images = self._images(tokens.shape[0], tokens.device)
        proposals, rpn_losses = self.rpn(images, maps, tv_targets)
        _, box_losses = self.roi_heads(maps, proposals, images.image_sizes, tv_targets)
        return {**rpn_losses, **box_losses}

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        if torch.jit.is_tracing() or torch.onnx.is_in_onnx_export():
            # ONNX has no export of vpengine::greedy_nms; the traced torchvision path keeps its NMS op (see
            # onnx_exporter above)
            return self.forward_reference(inputs)
        return detection_static.detect(self, inputs[self.layer])

    def forward_reference(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """:meth:`forward` through torchvision's RPN and RoIHeads (data-dependent shapes, host syncs): the reference
        the static path equals (Note [Static detection])."""
        dets = self.predict(inputs[self.layer])
        fixed = [self._fixed_capacity(det) for det in dets]
        return {k: torch.stack([f[k] for f in fixed]) for k in self.output_spec}

    def _fixed_capacity(self, det: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """One frame's detections in the fixed-capacity output layout."""
        m = self.opts.max_detections
        # Fixed capacity M: the first M detections (RoIHeads already keeps at most M, so the slot never overflows),
        # padded by concatenation and gathered at indices 0..M-1, so the shape is M even to a graph's shape inference.
        # Everything stays a tensor op -- no Python int from a data-dependent size -- so a traced ONNX export keeps
        # the count live instead of freezing the one it saw.
        device = det["scores"].device
        first = torch.arange(m, device=device)
        scores = det["scores"][:m].float()
        count = torch.ones_like(scores, dtype=torch.int32).sum(dtype=torch.int32)
        boxes = torch.cat([det["boxes"][:m].float(), torch.zeros(m, 4, device=device)])[first]
        scores = torch.cat([scores, torch.zeros(m, device=device)])[first]
        labels = torch.cat([det["labels"][:m].to(torch.int32), torch.full((m,), -1, dtype=torch.int32, device=device)])[
            first
        ]
        return {"boxes": boxes, "scores": scores, "labels": labels, "count": count}

    def finalize(self, outputs: dict[str, np.ndarray]) -> dict[str, Any]:
        n = int(outputs["count"])
        return {**{k: outputs[k][:n] for k in ("boxes", "scores", "labels")}, "count": n}
