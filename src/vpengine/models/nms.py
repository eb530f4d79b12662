"""Exact greedy non-maximum suppression with static shapes and no host synchronisation.

Note [Exact static NMS]
~~~~~~~~~~~~~~~~~~~~~~~
torchvision's ``nms`` returns as many indices as it keeps, a number only the data knows: a host sync, a dynamic
shape, no CUDA graph. :func:`greedy_nms` answers with a keep mask over a fixed number ``T`` of candidates instead,
for ``N`` independent segments at once (frames, pyramid levels). The caller gives, per segment:

* the candidates already in the order torchvision's ``nms`` walks them: by score, descending, ties in the order of a
  stable sort (torchvision sorts with ``stable=True``);
* which of them are real (``valid``): padding and candidates a filter dropped (score threshold, degenerate boxes)
  are never kept and never suppress;
* a class per candidate: candidates of different classes never suppress each other, as in ``batched_nms``.

Candidate ``i`` is kept when it is valid and no kept candidate before it of the same class overlaps it with IoU
above the threshold: the greedy rule, the same set as torchvision's (not an approximation such as Fast/Matrix NMS).
The IoU is torchvision's float32 formula, ``inter / (area_i + area_j - inter)``, and torchvision compares it with
the threshold as a double; the threshold is rounded down to float32 here, which gives the same comparisons for every
float32 IoU. Bits can differ in the last place only where a compiler contracts a multiply-add (nvcc does in
torchvision's CUDA kernel, Triton here) or where ``batched_nms`` offsets boxes by class (its "coordinate trick",
which rounds the shifted coordinates): that changes a decision only for an IoU within a rounding error of the
threshold.

Two steps, as torchvision's CUDA kernel: (1) the pairwise mask, bit ``j % 32`` of word ``j // 32`` of row ``i`` set
when ``j > i``, same class and IoU above the threshold, computed in parallel; (2) the walk: rows in order, a kept
row ORs its mask into the set of removed candidates. On CUDA both are Triton kernels (``_triton_nms.py``; the walk
is one program per segment, 32 rows per step). Elsewhere torchvision's CPU ``nms`` itself runs per segment and
class. Both sit behind the custom op ``vpengine::greedy_nms``: ``torch.compile`` sees one opaque node (no unrolled
loop of ``T`` steps, no graph break) and a CUDA graph captures its kernels.
"""

from __future__ import annotations

import numpy as np
import torch
from torchvision.ops import nms


def threshold32(threshold: float) -> float:
    """The float32 ``t`` with ``iou > t`` exactly when ``iou > threshold`` for every float32 ``iou``.

    torchvision compares a float32 IoU with a double threshold. 0.7 rounds down to float32, but a threshold that
    rounds up would make ``iou > float32(threshold)`` false for an IoU equal to that float, which exceeds it."""
    t = np.float32(threshold)
    if float(t) > threshold:
        t = np.nextafter(t, np.float32(-np.inf))
    return float(t)


def _keep_cpu(boxes: torch.Tensor, valid: torch.Tensor, classes: torch.Tensor, threshold: float) -> torch.Tensor:
    # torchvision's own CPU kernel, one call per segment and class, on descending ranks so that it walks the
    # candidates in the order given
    keep = torch.zeros_like(valid)
    rank = torch.arange(valid.shape[1], 0, -1, dtype=torch.float32)
    for n in range(valid.shape[0]):
        for c in classes[n][valid[n]].unique().tolist():
            idx = torch.nonzero(valid[n] & (classes[n] == c)).flatten()
            keep[n, idx[nms(boxes[n, idx], rank[idx], threshold)]] = True
    return keep


@torch.library.custom_op("vpengine::greedy_nms", mutates_args=())
def _greedy_nms_op(boxes: torch.Tensor, valid: torch.Tensor, classes: torch.Tensor, threshold: float) -> torch.Tensor:
    if boxes.device.type == "cuda":
        from vpengine.models import _triton_nms

        return _triton_nms.launch(boxes, valid, classes, threshold32(threshold))
    return _keep_cpu(boxes.cpu(), valid.cpu(), classes.cpu(), threshold).to(valid.device)


@_greedy_nms_op.register_fake
def _(boxes: torch.Tensor, valid: torch.Tensor, classes: torch.Tensor, threshold: float) -> torch.Tensor:
    return torch.empty(valid.shape, dtype=torch.bool, device=valid.device)


def greedy_nms(boxes: torch.Tensor, valid: torch.Tensor, classes: torch.Tensor, threshold: float) -> torch.Tensor:
    """Keep mask ``bool[N, T]`` of greedy NMS over ``boxes: [N, T, 4]`` (x1, y1, x2, y2), in walking order, with
    ``valid: bool[N, T]`` and ``classes: int[N, T]`` (Note [Exact static NMS]). Suppression when IoU > threshold."""
    if boxes.dim() != 3 or boxes.shape[-1] != 4 or valid.shape != boxes.shape[:2] or classes.shape != valid.shape:
        raise ValueError(
            f"greedy_nms takes boxes [N, T, 4], valid and classes [N, T]; got {tuple(boxes.shape)}, "
            f"{tuple(valid.shape)}, {tuple(classes.shape)}"
        )
    return _greedy_nms_op(
        boxes.float().contiguous(), valid.bool().contiguous(), classes.to(torch.int32).contiguous(), threshold
    )
