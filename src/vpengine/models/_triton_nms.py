"""The Triton kernels of Note [Exact static NMS] (nms.py). Imported only where Triton is.

``launch`` runs them on any tensors Triton accepts: CUDA tensors, or CPU tensors under Triton's interpreter
(``TRITON_INTERPRET=1``, which the CPU tests use). As in ``_triton_upsample_argmax.py``, the kernels call only
Triton's builtins and this module's own jit functions (the interpreter cannot run the standard library's reductions
when Triton was first imported outside interpreter mode).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

#: Candidates one mask word covers (int32 words).
WORD = 32


@triton.jit
def _or_fn(a, b):
    return a | b


@triton.jit
def _mask_kernel(boxes, classes, mask, T, W, threshold, WORD: tl.constexpr):
    # One program: rows 32r..32r+31 against the 32 candidates of word c, of segment n. Bit j of a row's word: the row
    # suppresses candidate 32c + j. torchvision's IoU, operation for operation (Note [Exact static NMS]).
    n = tl.program_id(2).to(tl.int64)
    boxes += n * T * 4
    classes += n * T
    mask += n * W * WORD * W
    lanes = tl.arange(0, WORD)
    rows = tl.program_id(0) * WORD + lanes
    cols = tl.program_id(1) * WORD + lanes
    rm = rows < T
    cm = cols < T
    rx1 = tl.load(boxes + rows * 4 + 0, mask=rm, other=0.0)
    ry1 = tl.load(boxes + rows * 4 + 1, mask=rm, other=0.0)
    rx2 = tl.load(boxes + rows * 4 + 2, mask=rm, other=0.0)
    ry2 = tl.load(boxes + rows * 4 + 3, mask=rm, other=0.0)
    cx1 = tl.load(boxes + cols * 4 + 0, mask=cm, other=0.0)
    cy1 = tl.load(boxes + cols * 4 + 1, mask=cm, other=0.0)
    cx2 = tl.load(boxes + cols * 4 + 2, mask=cm, other=0.0)
    cy2 = tl.load(boxes + cols * 4 + 3, mask=cm, other=0.0)
    w = tl.maximum(tl.minimum(rx2[:, None], cx2[None, :]) - tl.maximum(rx1[:, None], cx1[None, :]), 0.0)
    h = tl.maximum(tl.minimum(ry2[:, None], cy2[None, :]) - tl.maximum(ry1[:, None], cy1[None, :]), 0.0)
    inter = w * h
    ra = (rx2 - rx1) * (ry2 - ry1)
    ca = (cx2 - cx1) * (cy2 - cy1)
    # rounded as the CPU divides: Triton's own fp32 `/` is an approximate division, a last bit off, which flips an
    # IoU that lies on the threshold (seen on an H200)
    iou = tl.math.div_rn(inter, ra[:, None] + ca[None, :] - inter)
    rc = tl.load(classes + rows, mask=rm, other=-1)
    cc = tl.load(classes + cols, mask=cm, other=-2)
    # padding rows and columns: 0/0 is NaN, never above the threshold, and masked besides
    hit = (iou > threshold) & (cols[None, :] > rows[:, None]) & (rc[:, None] == cc[None, :])
    hit = hit & rm[:, None] & cm[None, :]
    word = tl.reduce(hit.to(tl.int32) << lanes[None, :], 1, _or_fn)
    tl.store(mask + rows * W + tl.program_id(1), word)


@triton.jit
def _walk_kernel(mask, valid, keep, T, W, WORD: tl.constexpr, WPAD: tl.constexpr):
    # One program per segment walks its rows in order, a word (32 rows) per step. ``removed`` (one bit per candidate,
    # in registers) holds what earlier steps' kept rows suppress; inside a step the 32 rows are resolved one by one
    # from their own word of the mask (the block on the diagonal), then the kept rows' whole mask rows are ORed in.
    n = tl.program_id(0).to(tl.int64)
    mask += n * W * WORD * W
    valid += n * T
    keep += n * T
    lanes = tl.arange(0, WORD)
    words = tl.arange(0, WPAD)
    removed = tl.full([WPAD], 0, tl.int32)
    for w in range(0, W):
        rows = w * WORD + lanes
        v = tl.load(valid + rows, mask=rows < T, other=0).to(tl.int32)
        live = tl.reduce(v << lanes, 0, _or_fn) & ~tl.reduce(tl.where(words == w, removed, 0), 0, _or_fn)
        diag = tl.load(mask + rows * W + w)
        kept = live & 0
        for b in tl.static_range(WORD):
            take = (live >> b) & 1
            kept = kept | (take << b)
            d = tl.reduce(tl.where(lanes == b, diag, 0), 0, _or_fn)
            live = live & ~(d * take)
        bits = (kept >> lanes) & 1
        tl.store(keep + rows, bits.to(tl.int8), mask=rows < T)
        tile = tl.load(mask + rows[:, None] * W + words[None, :], mask=words[None, :] < W, other=0)
        removed = removed | tl.reduce(tl.where(bits[:, None] == 1, tile, 0), 0, _or_fn)


def launch(boxes: torch.Tensor, valid: torch.Tensor, classes: torch.Tensor, threshold: float) -> torch.Tensor:
    """Keep mask ``bool[N, T]`` for contiguous ``boxes: float32[N, T, 4]``, ``valid: bool[N, T]``, ``classes:
    int32[N, T]``, suppressing where the float32 IoU > ``threshold`` (rounded as ``nms.threshold32`` does; Note
    [Exact static NMS])."""
    n, t = valid.shape
    w = triton.cdiv(t, WORD)
    mask = torch.empty((n, w * WORD, w), dtype=torch.int32, device=boxes.device)
    keep = torch.empty((n, t), dtype=torch.int8, device=boxes.device)
    if n == 0 or t == 0:
        return keep.bool()
    # no fused multiply-adds: torchvision rounds every product of its IoU on its own
    _mask_kernel[(w, w, n)](boxes, classes, mask, t, w, threshold, WORD=WORD, enable_fp_fusion=False)
    wpad = triton.next_power_of_2(w)
    _walk_kernel[(n,)](mask, valid.view(torch.int8), keep, t, w, WORD=WORD, WPAD=wpad, num_warps=1 if wpad <= 64 else 4)
    return keep.view(torch.bool)
