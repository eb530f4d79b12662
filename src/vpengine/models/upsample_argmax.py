"""Per-pixel class of logits upsampled to the frame: ``argmax_k(bilinear_upsample(logits)[k])``.

Note [Fused upsample + argmax]
~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~
A segmentation head's logits live on the token grid ([B, K, h, w], 150 classes for ADE20K) and its output is one
class per frame pixel. Upsampling all classes first, as PyTorch does, writes and reads K full-resolution planes:
1.2 GB in float32 at 1080p. The PyTorch path (``upsample_argmax``) bounds that memory by upsampling a few classes at
a time, and ``torch.compile`` fuses the chunks into one kernel, but that kernel still interpolates every class at
every frame pixel, a large part of a depth + seg frame, and it fills the whole GPU, so the depth head's short
kernels wait behind it.

On CUDA with Triton installed, ``LinearSegHead`` (``options.upsample: auto``) runs two Triton kernels instead
(``_triton_upsample_argmax.py``), as the custom op ``vpengine::upsample_argmax``, which ``torch.compile`` traces and
CUDA graphs capture:

1. Candidate classes, one program per cell. Every output pixel interpolates the four source values of its cell
   (source pixel (y0, x0) and its right, lower and lower-right neighbours) with weights >= 0 that sum to 1, so class
   k's value there lies between the least and the greatest of its four. A class whose greatest is below the largest
   "least" of any class can never win in that cell. The rest (less a margin for float32 rounding: too many, never too
   few) are the cell's candidates, in increasing class order; a cell with more than ``MAX_CANDIDATES``, or with a NaN
   or an infinity among its values, searches every class.
2. The class map: each program takes a run of pixels of one output row, computes their source coordinates and
   bilinear weights as PyTorch does (``align_corners=False``), and keeps the running maximum over its cell's
   candidates in registers; it writes the class index in the output's dtype (uint8 / int16), so no int64 map and no
   cast follow. The upsampled logits are never written.

A batch of frames is one launch of each kernel: the frame is the last axis of both grids, and each program offsets
its pointers to its own frame's logits, candidates and class map, so a frame's class map never depends on the
other frames of its batch (tests: under Triton's interpreter on the CPU, and on CUDA in tests/gpu).

The result is the argmax of the float32 interpolation, the same with or without candidates (tested bit for bit): it
equals the float64 argmax except at near-ties (1-4 pixels in 10^6 in the tests), and PyTorch's on float32 logits up
to the last bit of rounding. PyTorch's eager CUDA path rounds the upsampled logits to the model's precision before
its argmax (float16: about 3 decimal digits), so on float16 logits the two disagree only where two classes are within
that rounding of each other, on class boundaries. Everywhere else (the CPU, ONNX export, no Triton, ``upsample:
torch``) the PyTorch path runs, and so it does, with a warning that says why, on a GPU Triton cannot compile for
(compute capability below 7.0; ``fused_unavailable``). Any other failure of the kernels (a broken toolchain, say)
stops the head at warm-up with the error, and ``upsample: torch`` is the way round it.

Why candidates: logits that change slowly from token to token, as a trained head's do, leave a cell few
candidates, so the class map reads a small fraction of the classes. Logits that are noise from token to token are
the worst case: most cells keep more than ``MAX_CANDIDATES`` and search every class through a class list per pixel,
which is slower than searching every class one class at a time for a whole row (this kernel's first version). A
block whose pixels all search every class could take that single-class loop again; that is written and passes the
CPU tests, but it is not in until a GPU has measured it.
"""

from __future__ import annotations

import functools
import os

import torch
import torch.nn.functional as F

#: Largest transient buffer of upsampled logits, in bytes, of the PyTorch path. 150 ADE20K classes at 1080p are
#: 1.2 GB in float32; upsampling a few classes at a time keeps the peak near this bound with an identical result.
UPSAMPLE_BUDGET_BYTES = 64 * 2**20


def upsample_argmax(
    logits: torch.Tensor, size: tuple[int, int], budget_bytes: int = UPSAMPLE_BUDGET_BYTES
) -> torch.Tensor:
    """``argmax_k(bilinear_upsample(logits)[:, k])`` for ``logits: [B, K, h, w]`` -> int64 ``[B, H, W]``, in
    PyTorch, for the whole batch at once.

    Upsampling is per channel, so a few classes at a time give exactly the values of one big resize; keeping the
    running maximum with a strict ``>`` keeps the first class on ties, like ``argmax`` over all classes.
    """
    h, w = size
    b, k = logits.shape[:2]
    per_class = b * h * w * logits.element_size()
    chunk = max(1, budget_bytes // max(per_class, 1))
    if chunk >= k:
        up = F.interpolate(logits, size=size, mode="bilinear", align_corners=False)
        return up.argmax(1)
    best_val: torch.Tensor | None = None
    best_idx = torch.empty(0)
    for c0 in range(0, k, chunk):
        up = F.interpolate(logits[:, c0 : c0 + chunk], size=size, mode="bilinear", align_corners=False)
        val, idx = up.max(1)
        if best_val is None:
            best_val, best_idx = val, idx
            continue
        better = val > best_val
        best_val = torch.where(better, val, best_val)
        best_idx = torch.where(better, idx + c0, best_idx)
    return best_idx


@functools.cache
def _triton_missing() -> str | None:
    try:
        import triton  # noqa: F401
    except ImportError as e:
        return f"Triton is not installed ({e})"
    return None


def fused_unavailable(device: torch.device, probe: bool = True) -> str | None:
    """Why the fused kernel cannot run on ``device`` (None: it can). Registers its op the first time it can.

    ``probe``: also ask the GPU whether Triton can compile for it; without, no CUDA context is made (for planning).
    Nothing is launched here: a model is built while another thread may be capturing a CUDA graph."""
    if device.type != "cuda":
        return f"it runs on CUDA only, not on {device.type}"
    if os.environ.get("TRITON_INTERPRET") == "1":
        return "TRITON_INTERPRET=1 is set (Triton's CPU interpreter)"
    missing = _triton_missing()
    if missing is not None:
        return missing
    from vpengine.models import _triton_upsample_argmax

    _triton_upsample_argmax.register()
    if not probe:
        return None
    index = device.index if device.index is not None else torch.cuda.current_device()
    return _probe(index)


@functools.cache
def _probe(index: int) -> str | None:
    major, minor = torch.cuda.get_device_capability(index)
    if major < 7:  # what Triton's CUDA backend compiles for
        return f"Triton needs a GPU of compute capability 7.0 or newer, and cuda:{index} is {major}.{minor}"
    return None


def fused_upsample_argmax(logits: torch.Tensor, size: tuple[int, int], dtype: torch.dtype) -> torch.Tensor:
    """The fused kernel (Note [Fused upsample + argmax]) on ``logits: [B, K, h, w]`` -> ``[B, H, W]`` of ``dtype``;
    it launches once per frame of the batch. ``fused_unavailable(logits.device)`` must be None."""
    return torch.ops.vpengine.upsample_argmax(logits, size[0], size[1], dtype)
