"""The Triton kernels of Note [Fused upsample + argmax] (upsample_argmax.py). Imported only where Triton is.

``launch`` runs them on any tensors Triton accepts: CUDA tensors, or CPU tensors under Triton's interpreter
(``TRITON_INTERPRET=1``, which the CPU tests use). A batch of frames is one launch of each kernel: the last axis of
each grid is the frame, and every program offsets its pointers to its frame's logits, candidates and class map. ``register`` makes them the custom op ``vpengine::upsample_argmax``,
which ``torch.compile`` traces into its graph (and CUDA graphs capture) like any other kernel.

Only Triton's builtins and this module's own jit functions are called from the kernels: the standard library's
(``tl.max``, ``tl.cumsum``, ...) are jit functions made when Triton is first imported, and the interpreter cannot run
those if that import was not already in interpreter mode.
"""

from __future__ import annotations

import threading

import torch
import triton
import triton.language as tl

#: Output pixels of one row per program, and the warps that compute them: for the class-map kernel at 1080p with
#: 150 classes every pair from 64 to 1024 pixels ran within about a tenth of a millisecond of the others on an H100,
#: and this pair was the fastest.
BLOCK = 128
NUM_WARPS = 2
#: Candidate classes kept per cell; a cell with more (or with a NaN or an infinity) searches every class.
MAX_CANDIDATES = 32
#: Classes one candidate program looks at together.
CLASS_BLOCK = 256


@triton.jit
def _max_fn(a, b):
    return tl.maximum(a, b)


@triton.jit
def _add_fn(a, b):
    return a + b


@triton.jit
def _corners(src, kk, m, h, w, y0, x0, y1, x1):
    # classes kk's values at a cell's four corners, in float32 (0 where m is false)
    plane = src + kk * h * w
    a = tl.load(plane + y0 * w + x0, mask=m, other=0.0).to(tl.float32)
    b = tl.load(plane + y0 * w + x1, mask=m, other=0.0).to(tl.float32)
    c = tl.load(plane + y1 * w + x0, mask=m, other=0.0).to(tl.float32)
    d = tl.load(plane + y1 * w + x1, mask=m, other=0.0).to(tl.float32)
    return a, b, c, d


@triton.jit
def _candidates_kernel(src, cand, count, K, h, w, MAX_CAND: tl.constexpr, CLASS_BLOCK: tl.constexpr):
    # One program per cell of one frame: the source pixel (y0, x0) and its right, lower and lower-right neighbours
    # (clamped at the edges), whose values every output pixel with that (y0, x0) interpolates with weights >= 0
    # summing to 1. So in that cell class k's value lies in [lo_k, hi_k], the min and max of its four, and a class
    # whose hi is below the largest lo can never win there: the class with that lo beats it everywhere in the cell.
    frame = tl.program_id(1).to(tl.int64)
    src += frame * K * h * w
    cand += frame * h * w * MAX_CAND
    count += frame * h * w
    cell = tl.program_id(0)
    y0 = cell // w
    x0 = cell % w
    y1 = tl.where(y0 < h - 1, y0 + 1, y0)
    x1 = tl.where(x0 < w - 1, x0 + 1, x0)
    ks = tl.arange(0, CLASS_BLOCK)
    best_lo = tl.full([CLASS_BLOCK], float("-inf"), tl.float32)
    size = tl.full([CLASS_BLOCK], 0.0, tl.float32)
    bad = tl.full([CLASS_BLOCK], 0, tl.int32)
    for k0 in range(0, K, CLASS_BLOCK):
        kk = k0 + ks
        m = kk < K
        a, b, c, d = _corners(src, kk, m, h, w, y0, x0, y1, x1)
        lo = tl.minimum(tl.minimum(a, b), tl.minimum(c, d))
        best_lo = tl.where(m, tl.maximum(best_lo, lo), best_lo)
        big = tl.maximum(tl.maximum(tl.abs(a), tl.abs(b)), tl.maximum(tl.abs(c), tl.abs(d)))
        size = tl.maximum(size, big)
        # NaN and infinities: leave this cell to the full search, which handles them as argmax does
        finite = (a - a == 0.0) & (b - b == 0.0) & (c - c == 0.0) & (d - d == 0.0)
        bad = tl.maximum(bad, (m & ~finite).to(tl.int32))
    threshold = tl.reduce(best_lo, 0, _max_fn)
    # Below the bound by more than float32 rounding can account for (a few units in the last place of the cell's
    # largest value): candidates may be too many, never too few.
    threshold = threshold - 1e-5 * tl.reduce(size, 0, _max_fn) - 1e-30
    n = tl.reduce(bad, 0, _max_fn) * (MAX_CAND + 1)
    for k0 in range(0, K, CLASS_BLOCK):
        kk = k0 + ks
        m = kk < K
        a, b, c, d = _corners(src, kk, m, h, w, y0, x0, y1, x1)
        hi = tl.maximum(tl.maximum(a, b), tl.maximum(c, d))
        keep = (m & (hi >= threshold)).to(tl.int32)
        slot = n + tl.associative_scan(keep, 0, _add_fn) - 1  # classes stay in increasing order
        tl.store(cand + cell * MAX_CAND + slot, kk, mask=(keep > 0) & (slot < MAX_CAND))
        n += tl.reduce(keep, 0, _add_fn)
    tl.store(count + cell, tl.where(n > MAX_CAND, -1, n))


@triton.jit
def _upsample_argmax_kernel(
    src, dst, cand, count, K, h, w, H, W, scale_h, scale_w, MAX_CAND: tl.constexpr, BLOCK: tl.constexpr
):
    # One program: BLOCK pixels of output row ``row`` of frame ``frame``. Source coordinates as PyTorch's bilinear upsampling with
    # align_corners=False (area_pixel_compute_source_index): (dst + 0.5) * in / out - 0.5, clamped at 0; the
    # neighbour is the next row/column except on the last one. In float32 like PyTorch's kernel, also where a
    # caller passes the scales as float64 (torch.compile's launcher does).
    scale_h = tl.cast(scale_h, tl.float32)
    scale_w = tl.cast(scale_w, tl.float32)
    frame = tl.program_id(2).to(tl.int64)
    src += frame * K * h * w
    dst += frame * H * W
    cand += frame * h * w * MAX_CAND
    count += frame * h * w
    row = tl.program_id(1)
    cols = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    mask = cols < W
    sy = tl.maximum(scale_h * (row.to(tl.float32) + 0.5) - 0.5, 0.0)
    y0 = sy.to(tl.int32)
    y1 = tl.where(y0 < h - 1, y0 + 1, y0)
    ly1 = sy - y0.to(tl.float32)
    ly0 = 1.0 - ly1
    sx = tl.maximum(scale_w * (cols.to(tl.float32) + 0.5) - 0.5, 0.0)
    x0 = sx.to(tl.int32)
    x1 = tl.where(x0 < w - 1, x0 + 1, x0)
    lx1 = sx - x0.to(tl.float32)
    lx0 = 1.0 - lx1
    p00 = y0 * w + x0
    p01 = y0 * w + x1
    p10 = y1 * w + x0
    p11 = y1 * w + x1
    # Each pixel searches its cell's candidate classes (_candidates_kernel), or all classes where the cell has too
    # many; the loop runs as long as the longest search among this program's pixels.
    cell = p00
    n = tl.load(count + cell, mask=mask, other=0)
    every = n < 0
    n = tl.where(every, K, n)
    longest = tl.reduce(n, 0, _max_fn)
    best = tl.full([BLOCK], float("-inf"), tl.float32)
    idx = tl.full([BLOCK], 0, tl.int32)
    # The running maximum never leaves registers: neither the upsampled logits (1.2 GB for 150 classes at 1080p in
    # float32) nor a chunk of them is ever written. Neighbouring pixels read the same source values from cache.
    for j in range(0, longest):
        live = mask & (j < n)
        listed = tl.load(cand + cell * MAX_CAND + j, mask=live & ~every & (j < MAX_CAND), other=0)
        k = tl.where(every, j, listed)
        plane = src + k * h * w
        v00 = tl.load(plane + p00, mask=live, other=0.0).to(tl.float32)
        v01 = tl.load(plane + p01, mask=live, other=0.0).to(tl.float32)
        v10 = tl.load(plane + p10, mask=live, other=0.0).to(tl.float32)
        v11 = tl.load(plane + p11, mask=live, other=0.0).to(tl.float32)
        v = ly0 * (lx0 * v00 + lx1 * v01) + ly1 * (lx0 * v10 + lx1 * v11)
        # classes come in increasing order: strict '>' keeps the first on ties; a NaN wins over numbers and the
        # first NaN stays, as with argmax
        better = live & ((v > best) | ((v != v) & (best == best)))
        best = tl.where(better, v, best)
        idx = tl.where(better, k, idx)
    tl.store(dst + row * W + cols, idx.to(dst.dtype.element_ty), mask=mask)


def _run(cand_kernel, kernel, logits, out, cand, count, max_cand: int, block: int, num_warps: int) -> None:  # type: ignore[no-untyped-def]
    """The two launches over the whole batch, with the kernels as given (plain, or wrapped for torch.compile)."""
    b, k, h, w = logits.shape
    oh, ow = out.shape[-2:]
    if max_cand > 0:
        cand_kernel[(h * w, b)](logits, cand, count, k, h, w, MAX_CAND=max_cand, CLASS_BLOCK=CLASS_BLOCK)
    else:
        count.fill_(-1)
    kernel[(triton.cdiv(ow, block), oh, b)](
        logits, out, cand, count, k, h, w, oh, ow, float(h) / oh, float(w) / ow,
        MAX_CAND=max(max_cand, 1), BLOCK=block, num_warps=num_warps,
    )  # fmt: skip


def _buffers(logits: torch.Tensor, max_cand: int) -> tuple[torch.Tensor, torch.Tensor]:
    cells = logits.shape[0] * logits.shape[-2] * logits.shape[-1]
    cand = torch.empty(cells * max(max_cand, 1), dtype=torch.int32, device=logits.device)
    return cand, torch.empty(cells, dtype=torch.int32, device=logits.device)


def launch(
    logits: torch.Tensor,
    out: torch.Tensor,
    block: int = BLOCK,
    num_warps: int = NUM_WARPS,
    max_candidates: int = MAX_CANDIDATES,
) -> torch.Tensor:
    """``out[b, y, x] = argmax_k bilinear(logits[b, k])[y, x]`` for contiguous ``logits: [B, K, h, w]`` and
    ``out: [B, H, W]`` (``[H, W]`` for one frame). Returns the candidate count of every cell, frame after frame (-1:
    all classes searched); ``max_candidates=0`` searches all classes everywhere."""
    if out.dim() == 2:
        out = out[None]
    if out.shape[0] != logits.shape[0]:
        raise ValueError(f"{logits.shape[0]} frames of logits but {out.shape[0]} class maps")
    cand, count = _buffers(logits, max_candidates)
    _run(
        _candidates_kernel,
        _upsample_argmax_kernel,
        logits,
        out,
        cand,
        count,
        max_candidates,
        block,
        num_warps,
    )
    return count


_registered = False
_register_lock = threading.Lock()  # thread mode builds its models in parallel threads


def register() -> None:
    """Define ``torch.ops.vpengine.upsample_argmax(logits, height, width, dtype)``, once per process."""
    global _registered
    with _register_lock:
        if not _registered:
            _define()
            _registered = True


def _define() -> None:
    from torch.library import triton_op, wrap_triton

    cand_kernel, kernel = wrap_triton(_candidates_kernel), wrap_triton(_upsample_argmax_kernel)

    @triton_op("vpengine::upsample_argmax", mutates_args={})
    def upsample_argmax(logits: torch.Tensor, height: int, width: int, dtype: torch.dtype) -> torch.Tensor:
        logits = logits.contiguous()
        out = torch.empty((logits.shape[0], height, width), dtype=dtype, device=logits.device)
        cand, count = _buffers(logits, MAX_CANDIDATES)
        _run(cand_kernel, kernel, logits, out, cand, count, MAX_CANDIDATES, BLOCK, NUM_WARPS)
        return out
