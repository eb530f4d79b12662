"""Exact static NMS (Note [Exact static NMS]): the keep mask equals torchvision's batched_nms, on the CPU path and
on the Triton kernels under Triton's interpreter."""

from __future__ import annotations

import pytest
import torch

from helpers.detection import crowded, static_keep, torchvision_keep
from helpers.triton_interpreter import interpreted
from vpengine.models.nms import greedy_nms, threshold32


@pytest.mark.parametrize("threshold", [0.3, 0.5, 0.7, 1.0])
@pytest.mark.parametrize("t", [1, 31, 32, 33, 200])
def test_static_nms_keeps_what_batched_nms_keeps(threshold, t):
    boxes, scores, labels, valid = crowded(4, t, seed=t)
    want = torchvision_keep(boxes, scores, labels, valid, threshold)
    got = static_keep(greedy_nms, boxes, scores, labels, valid, threshold)
    assert got == want
    if t == 200:  # the crowd makes NMS matter: many valid boxes are suppressed, and by their own class only
        kept, n_valid = sum(map(len, got)), int(valid.sum())
        one_class = sum(map(len, static_keep(greedy_nms, boxes, scores, torch.zeros_like(labels), valid, threshold)))
        if threshold < 1.0:
            assert one_class < kept < n_valid
        else:  # an IoU is never above 1
            assert kept == one_class == n_valid


def test_threshold_rounds_so_float32_comparisons_match_double_ones():
    for t in (0.1, 0.3, 0.5, 0.7, 1 / 3, 0.9999999):
        f = torch.tensor(threshold32(t), dtype=torch.float32)
        up = torch.nextafter(f, torch.tensor(2.0))
        assert float(f) <= t < float(up) or float(f) == t  # the largest float32 not above t
        assert not float(f) > t


@pytest.fixture
def kernel(monkeypatch):
    """The Triton NMS kernels built for Triton's interpreter (CPU tensors), rebuilt as usual after."""
    yield from interpreted(monkeypatch, "vpengine.models._triton_nms")


# The interpreter runs a kernel's programs one by one in Python: few and small cases (the GPU test runs thousands).
# 70 candidates are three mask words, padded to four in the walk's registers.
@pytest.mark.parametrize(("t", "threshold"), [(1, 0.5), (32, 0.7), (45, 0.5), (70, 0.7)])
def test_triton_kernels_keep_what_batched_nms_keeps(kernel, t, threshold):
    boxes, scores, labels, valid = crowded(3, t, seed=100 + t)
    want = torchvision_keep(boxes, scores, labels, valid, threshold)

    def launch(b, v, c, thr):
        return kernel.launch(b.contiguous(), v.contiguous(), c.to(torch.int32).contiguous(), threshold32(thr))

    assert static_keep(launch, boxes, scores, labels, valid, threshold) == want


@pytest.mark.parametrize("wpad", [1, 64, 256])
def test_triton_kernels_compile_for_a_gpu(wpad):
    # Triton's compiler runs without a GPU: type errors that its CPU interpreter lets pass fail here, not on a robot
    triton = pytest.importorskip("triton")
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from vpengine.models import _triton_nms as module

    sizes = {"T": "i32", "W": "i32"}
    kernels = {
        module._mask_kernel: (
            {"boxes": "*fp32", "classes": "*i32", "mask": "*i32", **sizes, "threshold": "fp32", "WORD": "constexpr"},
            {"WORD": module.WORD},
        ),
        module._walk_kernel: (
            {"mask": "*i32", "valid": "*i8", "keep": "*i8", **sizes, "WORD": "constexpr", "WPAD": "constexpr"},
            {"WORD": module.WORD, "WPAD": wpad},
        ),
    }
    for fn, (signature, constants) in kernels.items():
        source = ASTSource(fn=fn, signature=signature, constexprs=constants)
        compiled = triton.compile(source, target=GPUTarget("cuda", 90, 32))  # an H100's / H200's architecture
        assert compiled.asm["cubin"], fn.__name__
