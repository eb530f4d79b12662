"""Faster R-CNN heads whose detections are worth comparing, and the comparison of the static path with torchvision's
(Note [Static detection]): same labels and counts, boxes within 0.5 px, scores within 1e-3."""

from __future__ import annotations

from typing import Any

import torch
from torchvision.ops import batched_nms

from helpers import heads
from vpengine.models.detection import FasterRCNNHead
from vpengine.models.training import _fit

DIM = 32
#: Small enough to build and run in milliseconds; the layout is the full recipe's.
SMALL = {"num_classes": 3, "out_channels": 16, "representation_size": 32, "rpn_post_nms_top_n_test": 300}


def build(
    frame: tuple[int, int], grid: tuple[int, int], options: dict[str, Any] | None = None, device: str = "cpu"
) -> FasterRCNNHead:
    head = {"name": "det", "model": "frcnn_dinov2", "options": {**SMALL, **(options or {})}}
    model = heads.build_head(heads.head_config(frame, head, device=device), grid, DIM, device)
    assert isinstance(model, FasterRCNNHead)
    return model.eval()


def tokens(head: FasterRCNNHead, batch: int, seed: int, device: str = "cpu") -> torch.Tensor:
    """Random features with some spatial structure (a blob per frame), so objectness is not noise everywhere."""
    g = torch.Generator().manual_seed(seed)
    gh, gw = head.grid
    x = torch.randn(batch, gh * gw, head.dim, generator=g)
    ys, xs = torch.meshgrid(torch.arange(gh), torch.arange(gw), indexing="ij")
    for b in range(batch):
        cy, cx = torch.rand(2, generator=g) * torch.tensor([gh, gw])
        blob = torch.exp(-((ys - cy) ** 2 + (xs - cx) ** 2) / 4).flatten()
        x[b] += 3 * blob[:, None] * torch.randn(head.dim, generator=g)
    return x.to(device)


def spread_(head: FasterRCNNHead, seed: int = 0) -> FasterRCNNHead:
    """Scale random weights so scores and boxes spread out.

    Fresh random weights give an RPN whose objectness is ~0.5 everywhere (std-0.01 init) and a classifier whose
    softmax is near uniform: scores tie or nearly tie, so which box NMS keeps turns on the last bits and the
    comparison would test rounding, not the algorithm. Scaled up, objectness and class scores cover (0, 1) and
    proposals move off their anchors, as a trained head's do."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        head.rpn.head.cls_logits.weight.mul_(300)
        head.rpn.head.bbox_pred.weight.mul_(30)
        pred = head.roi_heads.box_predictor
        pred.cls_score.weight.mul_(8)
        pred.cls_score.bias.copy_(torch.randn(pred.cls_score.bias.shape, generator=g))
        pred.bbox_pred.weight.mul_(4)
    return head


def train_(head: FasterRCNNHead, epochs: int = 3, seed: int = 0) -> FasterRCNNHead:
    """A few epochs of ``vpengine train detector``'s optimisation (``training._fit``) on synthetic boxes."""
    g = torch.Generator().manual_seed(seed)
    h, w = head.input_hw
    feats, targets = [], []
    for i in range(8):
        feats.append(tokens(head, 1, seed=1000 + i))
        xy = torch.rand(3, 2, generator=g) * torch.tensor([w * 0.6, h * 0.6])
        wh = (0.2 + 0.2 * torch.rand(3, 2, generator=g)) * torch.tensor([w, h])
        targets.append({"boxes": torch.cat([xy, xy + wh], 1), "labels": torch.randint(0, 3, (3,), generator=g)})
    head.requires_grad_(True)
    _fit(head, feats, targets, torch.device("cpu"), epochs, 3e-3, 1e-4, 2, seed, False, None)
    return head.eval().requires_grad_(False)


def assert_same_detections(got: dict[str, torch.Tensor], want: dict[str, torch.Tensor], what: str) -> None:
    """Per frame: the same count and labels, boxes within 0.5 input pixels, scores within 1e-3."""
    got = {k: v.detach().cpu() for k, v in got.items()}
    want = {k: v.detach().cpu() for k, v in want.items()}
    assert got["count"].tolist() == want["count"].tolist(), f"{what}: counts"
    for i, n in enumerate(want["count"].tolist()):
        assert got["labels"][i].tolist() == want["labels"][i].tolist(), f"{what}, frame {i}: labels"
        torch.testing.assert_close(got["boxes"][i, :n], want["boxes"][i, :n], rtol=0, atol=0.5, msg=what)
        torch.testing.assert_close(got["scores"][i, :n], want["scores"][i, :n], rtol=0, atol=1e-3, msg=what)
        assert (got["boxes"][i, n:] == 0).all() and (got["scores"][i, n:] == 0).all(), f"{what}: padding"


# ------------------------------------------------------------------------------------------ NMS
def crowded(n: int, t: int, seed: int, classes: int = 3) -> tuple[torch.Tensor, ...]:
    """``n`` segments of ``t`` boxes piled onto a 56x56 area, so most pairs overlap, with many tied scores.

    Integer coordinates make every IoU the same float in torchvision's batched_nms (which shifts boxes by class
    before its nms when there are few) and here, and they give IoUs of exactly 0.5 and other ties with the
    threshold, where suppression must need IoU strictly above it."""
    g = torch.Generator().manual_seed(seed)
    xy = torch.randint(0, 24, (n, t, 2), generator=g).float()
    wh = torch.randint(4, 32, (n, t, 2), generator=g).float()
    boxes = torch.cat([xy, xy + wh], -1)
    scores = torch.randint(0, 12, (n, t), generator=g).float() / 12  # ties everywhere
    labels = torch.randint(0, classes, (n, t), generator=g)
    valid = torch.rand(n, t, generator=g) > 0.2
    return boxes, scores, labels, valid


def torchvision_keep(boxes, scores, labels, valid, threshold) -> list[set[int]]:
    """Per segment: indices kept by torchvision's batched_nms among the valid boxes."""
    out = []
    for b, s, c, v in zip(boxes, scores, labels, valid):
        idx = torch.nonzero(v).flatten()
        out.append(set(idx[batched_nms(b[idx], s[idx], c[idx], threshold)].tolist()))
    return out


def static_keep(nms, boxes, scores, labels, valid, threshold) -> list[set[int]]:
    """Per segment: indices kept by the static NMS after sorting as the caller must (stable, descending)."""
    order = scores.sort(dim=1, descending=True, stable=True).indices
    take = order[..., None].expand(-1, -1, 4)
    keep = nms(boxes.gather(1, take), valid.gather(1, order), labels.gather(1, order), threshold)
    assert keep.dtype == torch.bool and keep.shape == valid.shape
    return [set(o[k].tolist()) for o, k in zip(order, keep)]
