"""The Faster R-CNN head's inference path with static shapes (Note [Static detection]).

Note [Static detection]
~~~~~~~~~~~~~~~~~~~~~~~
torchvision's RPN and RoIHeads filter boxes by score and size and run NMS on whatever survives: every frame has its
own box counts, read on the host (``.item()``, ``nonzero``, boolean indexing), so the head cannot be one CUDA graph
and stalls its stream a few times per frame. This path computes the same detections from the same modules and
weights with every shape fixed by the config, for a batch of frames at once:

1. Proposals. Per pyramid level, the top ``n_l = min(rpn_pre_nms_top_n_test, anchors of the level)`` anchors by
   objectness (torchvision's ``topk``, so the same order), decoded and clipped to the image. torchvision's filters
   (sides >= 1e-3, objectness >= ``rpn_score_threshold``) become a validity mask. NMS per level and frame
   (Note [Exact static NMS] in nms.py): the ``topk`` order is the walking order, since torchvision's stable sort
   keeps it. The kept boxes of all levels are merged by one stable sort by score (ties in level order, as in
   torchvision's concatenation), the first ``P = min(rpn_post_nms_top_n_test, sum n_l)`` being the proposals, with
   a count.
2. Box head on all ``P`` proposal slots of every frame (slots past the count hold a unit box and are never
   candidates). RoIAlign pools every proposal on every level and keeps, per proposal, the level torchvision's
   level mapper assigns: the same values as torchvision's per-level pooling, at L times its (small) cost, and no
   data-dependent split.
3. Detections. Decoded, clipped boxes and softmax scores per (proposal, class), background dropped; candidates are
   those of a counted proposal with score > ``score_threshold`` and sides >= 1e-2 (torchvision's filters). The first
   ``T`` candidates in torchvision's order (stable sort by score over proposal-major, class-minor order) go through
   NMS per class. ``T`` holds every candidate there can be: one proposal's class scores sum to 1 (up to rounding), so
   fewer than ``1 / score_threshold`` of them exceed the threshold, and ``T = P * min(classes, that bound)``; a
   threshold of 0 makes it every class. Then, as ``predict`` does: the first ``max_detections`` kept, mapped to input
   pixels, those narrower or shorter than ``min_size`` dropped, compacted into the fixed-capacity outputs.

Nothing reads a value on the host, so the head compiles with ``fullgraph`` and runs as one CUDA graph per batch
size; the torchvision path (``FasterRCNNHead.predict``) stays for training, ONNX export and as the reference that
tests compare this path with.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torchvision.models.detection.rpn import concat_box_prediction_layers
from torchvision.ops import boxes as box_ops
from torchvision.ops import roi_align

from vpengine.models.nms import greedy_nms

if TYPE_CHECKING:
    from torchvision.models.detection._utils import BoxCoder

    from vpengine.models.detection import FasterRCNNHead

#: torchvision's fixed minimum box sides: RegionProposalNetwork.min_size and RoIHeads.postprocess_detections'.
RPN_MIN_SIDE = 1e-3
BOX_MIN_SIDE = 1e-2
#: How far above 1 a softmax's float32 sum may be, for the bound on candidates per proposal (Note [Static detection]).
SOFTMAX_SLACK = 1e-4


def candidates_per_proposal(classes: int, score_threshold: float) -> int:
    """Most classes of one proposal whose softmax score can exceed ``score_threshold`` (Note [Static detection])."""
    if score_threshold <= 0:
        return classes
    return max(1, min(classes, math.ceil((1 + SOFTMAX_SLACK) / score_threshold) - 1))


def _big_enough(boxes: torch.Tensor, side: float) -> torch.Tensor:
    # remove_small_boxes' test, as a mask
    return ((boxes[..., 2] - boxes[..., 0]) >= side) & ((boxes[..., 3] - boxes[..., 1]) >= side)


def _gather(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``x[b, idx[b, i], ...]`` for ``x: [B, N, ...]``, ``idx: [B, K]``."""
    return x.gather(1, idx.view(*idx.shape, *([1] * (x.dim() - 2))).expand(*idx.shape, *x.shape[2:]))


def _decode(coder: BoxCoder, rel_codes: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """torchvision's ``BoxCoder.decode`` of ``rel_codes: [N, 4 * C]`` against ``boxes: [N, 4]``, the same arithmetic
    in the same order, without its host-to-device copy of the constant 0.5 (a copy from pageable memory, which waits
    for the stream on CUDA)."""
    boxes = boxes.to(rel_codes.dtype)
    widths = boxes[:, 2] - boxes[:, 0]
    heights = boxes[:, 3] - boxes[:, 1]
    ctr_x = boxes[:, 0] + 0.5 * widths
    ctr_y = boxes[:, 1] + 0.5 * heights
    wx, wy, ww, wh = coder.weights
    dx = rel_codes[:, 0::4] / wx
    dy = rel_codes[:, 1::4] / wy
    dw = torch.clamp(rel_codes[:, 2::4] / ww, max=coder.bbox_xform_clip)
    dh = torch.clamp(rel_codes[:, 3::4] / wh, max=coder.bbox_xform_clip)
    pred_ctr_x = dx * widths[:, None] + ctr_x[:, None]
    pred_ctr_y = dy * heights[:, None] + ctr_y[:, None]
    half_w = 0.5 * (torch.exp(dw) * widths[:, None])
    half_h = 0.5 * (torch.exp(dh) * heights[:, None])
    corners = (pred_ctr_x - half_w, pred_ctr_y - half_h, pred_ctr_x + half_w, pred_ctr_y + half_h)
    return torch.stack(corners, dim=2).flatten(1)


def proposals(head: FasterRCNNHead, maps: OrderedDict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 1: ``boxes float32[B, P, 4]`` (preprocessed-image pixels, best first) and ``valid bool[B, P]``."""
    rpn = head.rpn
    feats = list(maps.values())
    b = feats[0].shape[0]
    objectness, deltas = rpn.head(feats)
    # every frame's anchors are the same: one frame's, repeated (a list of b would fix b: Note [One compile for
    # every batch] in backends/compiled.py)
    anchors = rpn.anchor_generator(head._images(1, feats[0].device), feats)[0].repeat(b, 1)
    per_level = [o.shape[1] * o.shape[2] * o.shape[3] for o in objectness]
    obj, deltas = concat_box_prediction_layers(objectness, deltas)
    decoded = _decode(rpn.box_coder, deltas.detach().reshape(-1, 4), anchors).view(b, -1, 4)
    obj = obj.view(b, -1)
    top = [min(rpn.pre_nms_top_n(), k) for k in per_level]
    width = max(top)
    level_boxes, level_scores, level_valid = [], [], []
    start = 0
    for k, n in zip(per_level, top):
        logit, idx = obj[:, start : start + k].topk(n, dim=1)
        boxes = box_ops.clip_boxes_to_image(_gather(decoded[:, start : start + k], idx), head.image_hw)
        scores = torch.sigmoid(logit)
        valid = _big_enough(boxes, RPN_MIN_SIDE) & (scores >= rpn.score_thresh)
        pad = width - n  # levels with fewer anchors than the widest one: padding, never valid
        level_boxes.append(F.pad(boxes, (0, 0, 0, pad)))
        level_scores.append(F.pad(scores, (0, pad)))
        level_valid.append(F.pad(valid.to(torch.uint8), (0, pad)).bool())
        start += k
    boxes = torch.stack(level_boxes, 1)  # [B, L, width, 4]
    valid = torch.stack(level_valid, 1)
    no_class = torch.zeros(valid.shape[0] * valid.shape[1], width, dtype=torch.int32, device=valid.device)
    keep = greedy_nms(boxes.flatten(0, 1), valid.flatten(0, 1), no_class, rpn.nms_thresh).view(b, -1)
    # objectness is in [0, 1]: -1 sorts every dropped box after every kept one
    key = torch.where(keep, torch.stack(level_scores, 1).view(b, -1), -1.0)
    p = min(rpn.post_nms_top_n(), sum(top))
    order = key.sort(dim=1, descending=True, stable=True).indices[:, :p]
    count = keep.sum(1, keepdim=True)
    return _gather(boxes.view(b, -1, 4), order), torch.arange(p, device=keep.device) < count


def pooled_features(
    head: FasterRCNNHead, maps: OrderedDict[str, torch.Tensor], boxes: torch.Tensor, valid: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Step 2's RoIAlign: ``[B * P, C, S, S]`` features of every proposal slot, and the boxes it pooled."""
    pool = head.roi_heads.box_roi_pool
    b, p = valid.shape
    unit = (torch.arange(4, device=boxes.device) >= 2).to(boxes.dtype)  # [0, 0, 1, 1], without a host copy
    flat = torch.where(valid[..., None], boxes, unit).reshape(b * p, 4)
    frame = torch.arange(b, device=boxes.device, dtype=flat.dtype)[:, None].expand(b, p).reshape(b * p)
    rois = torch.cat([frame[:, None], flat], 1)  # torchvision's roi format: frame index, x1, y1, x2, y2
    feats = [maps[name] for name in pool.featmap_names]
    levels = pool.map_levels([flat]) if len(feats) > 1 else None
    per_level = [
        roi_align(f, rois, output_size=pool.output_size, spatial_scale=scale, sampling_ratio=pool.sampling_ratio)
        for f, scale in zip(feats, pool.scales)
    ]
    pooled = per_level[0].to(feats[0].dtype)
    if levels is not None:
        for level, r in enumerate(per_level[1:], 1):
            pooled = torch.where((levels == level)[:, None, None, None], r.to(pooled.dtype), pooled)
    return pooled, flat


def detect(head: FasterRCNNHead, tokens: torch.Tensor) -> dict[str, torch.Tensor]:
    """The fixed-capacity outputs of ``FasterRCNNHead.forward`` for ``tokens: [B, h*w, C]``, in eval mode."""
    if head.training:
        raise RuntimeError("the static detection path runs in eval mode; call .eval() first (training uses losses())")
    maps = head.feature_maps(tokens)
    boxes, valid = proposals(head, maps)
    return detections(head, maps, boxes, valid)


def detections(
    head: FasterRCNNHead, maps: OrderedDict[str, torch.Tensor], boxes: torch.Tensor, valid: torch.Tensor
) -> dict[str, torch.Tensor]:
    """Steps 2 and 3 from ``boxes: [B, P, 4]`` proposals of which ``valid`` count (Note [Static detection])."""
    rh = head.roi_heads
    b, p = valid.shape
    pooled, flat = pooled_features(head, maps, boxes, valid)
    logits, deltas = rh.box_predictor(rh.box_head(pooled))
    pred = box_ops.clip_boxes_to_image(_decode(rh.box_coder, deltas, flat), head.image_hw)
    scores = F.softmax(logits, -1)
    k = scores.shape[-1] - 1  # column 0 is the background
    pred = pred.view(b, p, k + 1, 4)[:, :, 1:].reshape(b, p * k, 4)
    scores = scores.view(b, p, k + 1)[:, :, 1:].reshape(b, p * k)
    labels = torch.arange(k, device=scores.device, dtype=torch.int32).repeat(p)  # label - 1: our class index
    ok = (
        valid[:, :, None].expand(b, p, k).reshape(b, p * k)
        & (scores > rh.score_thresh)
        & _big_enough(pred, BOX_MIN_SIDE)
    )
    t = p * candidates_per_proposal(k, rh.score_thresh)
    # softmax scores are in [0, 1]: -1 sorts every non-candidate after every candidate
    order = torch.where(ok, scores, -1.0).sort(dim=1, descending=True, stable=True).indices[:, :t]
    pred, scores, ok, labels = _gather(pred, order), _gather(scores, order), _gather(ok, order), labels[order]
    keep = greedy_nms(pred, ok, labels, rh.nms_thresh)
    m = head.opts.max_detections
    out_boxes = head.boxes_to_input(pred.reshape(-1, 4)).view(b, t, 4)
    # predict(): RoIHeads keeps the first M, then slivers narrower than min_size input pixels go
    wide = ((out_boxes[..., 2:] - out_boxes[..., :2]) >= head.opts.min_size).all(-1)
    final = keep & (keep.cumsum(1) <= m) & wide
    # compaction: detection i goes to slot (its rank among the final ones); the rest to a slot past M, cut off
    slot = torch.where(final, final.cumsum(1) - 1, m)
    zeros = torch.zeros(b, m + 1, 4, device=pred.device)
    return {
        "boxes": zeros.scatter(1, slot[..., None].expand(-1, -1, 4), out_boxes)[:, :m],
        "scores": zeros[..., 0].scatter(1, slot, scores.float())[:, :m],
        "labels": torch.full((b, m + 1), -1, dtype=torch.int32, device=pred.device).scatter(1, slot, labels)[:, :m],
        "count": final.sum(1, dtype=torch.int32),
    }
