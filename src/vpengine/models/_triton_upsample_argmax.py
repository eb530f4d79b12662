"""The Triton kernel of Note [Fused upsample + argmax] (upsample_argmax.py). Imported only where Triton is.

``launch`` runs the kernel on any tensors Triton accepts: CUDA tensors, or CPU tensors under Triton's interpreter
(``TRITON_INTERPRET=1``, which the CPU tests use). ``register`` makes it the custom op ``vpengine::upsample_argmax``,
which ``torch.compile`` traces into its graph (and CUDA graphs capture) like any other kernel.
"""

from __future__ import annotations

import threading

import torch
import triton
import triton.language as tl

#: Output pixels of one row per program, and the warps that compute them: at 1080p with 150 classes on an H100, 128
#: and 2 took 0.47 ms, every pair from 64 to 1024 pixels 0.47-0.58 ms (benchmarks/results/h100/upsample_argmax_sweep.json)
BLOCK = 128
NUM_WARPS = 2


@triton.jit
def _upsample_argmax_kernel(src, dst, K, h, w, W, scale_h, scale_w, BLOCK: tl.constexpr):
    # One program: BLOCK pixels of output row ``row``. Source coordinates as PyTorch's bilinear upsampling with
    # align_corners=False (area_pixel_compute_source_index): (dst + 0.5) * in / out - 0.5, clamped at 0; the
    # neighbour is the next row/column except on the last one.
    # In float32 like PyTorch's kernel (whose coordinates are float32), also where a caller passes the scales as
    # float64 (torch.compile's launcher does)
    scale_h = tl.cast(scale_h, tl.float32)
    scale_w = tl.cast(scale_w, tl.float32)
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
    best = tl.full([BLOCK], float("-inf"), tl.float32)
    idx = tl.full([BLOCK], 0, tl.int32)
    # The running maximum over classes never leaves registers: neither the upsampled logits (1.2 GB for 150
    # classes at 1080p in float32) nor a chunk of them is ever written. Neighbouring pixels read the same four
    # source values, so the loads are served from cache.
    for k in range(0, K):
        plane = src + k * h * w
        v00 = tl.load(plane + p00, mask=mask, other=0.0).to(tl.float32)
        v01 = tl.load(plane + p01, mask=mask, other=0.0).to(tl.float32)
        v10 = tl.load(plane + p10, mask=mask, other=0.0).to(tl.float32)
        v11 = tl.load(plane + p11, mask=mask, other=0.0).to(tl.float32)
        v = ly0 * (lx0 * v00 + lx1 * v01) + ly1 * (lx0 * v10 + lx1 * v11)
        # strict '>' keeps the first class on ties; a NaN wins over numbers and the first NaN stays, as argmax
        better = (v > best) | ((v != v) & (best == best))
        best = tl.where(better, v, best)
        idx = tl.where(better, k, idx)
    tl.store(dst + row * W + cols, idx.to(dst.dtype.element_ty), mask=mask)


def launch(logits: torch.Tensor, out: torch.Tensor, block: int = BLOCK, num_warps: int = NUM_WARPS) -> None:
    """``out[y, x] = argmax_k bilinear(logits[0, k])[y, x]`` for contiguous ``logits: [1, K, h, w]``."""
    _, k, h, w = logits.shape
    oh, ow = out.shape
    grid = (triton.cdiv(ow, block), oh)
    _upsample_argmax_kernel[grid](
        logits, out, k, h, w, ow, float(h) / oh, float(w) / ow, BLOCK=block, num_warps=num_warps
    )


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

    kernel = wrap_triton(_upsample_argmax_kernel)

    @triton_op("vpengine::upsample_argmax", mutates_args={})
    def upsample_argmax(logits: torch.Tensor, height: int, width: int, dtype: torch.dtype) -> torch.Tensor:
        logits = logits.contiguous()
        out = torch.empty((height, width), dtype=dtype, device=logits.device)
        _, k, h, w = logits.shape
        grid = (triton.cdiv(width, BLOCK), height)
        kernel[grid](
            logits, out, k, h, w, width, float(h) / height, float(w) / width, BLOCK=BLOCK, num_warps=NUM_WARPS
        )
        return out
