"""The class map of upsampled logits: PyTorch's chunked path and the fused Triton kernel (run here by Triton's CPU
interpreter; tests/gpu/test_upsample_argmax_cuda.py runs it compiled on CUDA), both against float64 PyTorch."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from helpers.classmaps import assert_argmax_of, reference
from helpers.triton_interpreter import interpreted
from vpengine.models.upsample_argmax import upsample_argmax


def test_upsample_argmax_in_class_chunks_equals_one_big_resize_and_keeps_first_on_ties():
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(2, 23, 5, 7, generator=g)  # a batch of two frames
    logits[:, 15] = logits[:, 3]  # exact tie between classes 3 and 15: 3 must win, as with argmax
    size = (61, 83)
    full = F.interpolate(logits, size=size, mode="bilinear", align_corners=False).argmax(1)
    per_class = 2 * size[0] * size[1] * 4
    for chunk in (1, 4, 7, 22, 23, 100):
        got = upsample_argmax(logits, size, budget_bytes=chunk * per_class)
        assert torch.equal(got, full), chunk
        for i in range(2):  # each frame as if alone
            assert torch.equal(upsample_argmax(logits[i : i + 1], size, budget_bytes=chunk * per_class)[0], full[i])
    assert not (full == 15).any() and (full == 3).any()


# ------------------------------------------------------------------------------------ the fused kernel
@pytest.fixture
def kernel(monkeypatch):
    """The kernel module with its kernel built for Triton's interpreter (CPU tensors), rebuilt as usual after."""
    yield from interpreted(monkeypatch, "vpengine.models._triton_upsample_argmax")


@pytest.mark.parametrize(
    "k, src, dst",
    [
        # token grids of few cells: Triton's interpreter runs one candidate program per cell, and slowly
        (5, (3, 4), (17, 23)),  # upsampling by uneven factors
        (23, (3, 4), (13, 3)),  # up in one direction, down in the other
        (3, (4, 4), (3, 3)),  # down
        (21, (3, 4), (3, 4)),  # same size: the logits' own argmax
        (4, (1, 1), (6, 9)),  # one source pixel
        (1, (3, 3), (10, 10)),  # one class
    ],
    ids=lambda v: "x".join(map(str, v)) if isinstance(v, tuple) else str(v),
)
def test_fused_kernel_is_the_argmax_of_bilinear_upsampling(kernel, k, src, dst):
    logits = torch.randn(1, k, *src, generator=torch.Generator().manual_seed(k))
    out = torch.full(dst, 255, dtype=torch.uint8)
    kernel.launch(logits, out)
    up, best = reference(logits, dst)
    assert_argmax_of(out, up, best)
    if src == dst:
        assert torch.equal(out.long(), logits[0].argmax(0))


def test_fused_kernel_runs_a_batch_in_one_launch_each_frame_as_if_alone(kernel):
    # one program grid over every frame: each must read its own logits and candidates and write its own map
    g = torch.Generator().manual_seed(5)
    # a small token grid (Triton's interpreter runs one program per token cell) and a map of several pixel blocks
    logits = torch.cat([smooth_logits(9, (2, 3), seed=6), torch.randn(1, 9, 2, 3, generator=g)])  # few, many
    logits = torch.cat([logits, logits[:1] * -1])  # a third frame whose classes win elsewhere
    out = torch.full((3, 9, 11), 255, dtype=torch.uint8)
    counts = kernel.launch(logits, out, max_candidates=4).view(3, 2, 3)
    for i in range(3):
        alone = torch.full((9, 11), 255, dtype=torch.uint8)
        alone_counts = kernel.launch(logits[i : i + 1], alone, max_candidates=4).view(2, 3)
        assert torch.equal(out[i], alone), i
        assert torch.equal(counts[i], alone_counts), i
        up, best = reference(logits[i : i + 1], (9, 11))
        assert_argmax_of(out[i], up, best)
    assert not torch.equal(out[0], out[2])
    assert (counts == -1).any() and (counts > 0).any(), counts  # cells of both searches: listed and every class
    with pytest.raises(ValueError, match="3 frames of logits but 2 class maps"):
        kernel.launch(logits, out[:2])


def test_fused_kernel_keeps_the_first_class_on_ties_and_writes_int16(kernel):
    logits = torch.randn(1, 300, 2, 3, generator=torch.Generator().manual_seed(1)) * 0.1
    logits[:, 280] += 1.0  # a class beyond int8 range wins in most places...
    logits[:, 290] = logits[:, 280]  # ...tied with a later one, which must never win
    out = torch.zeros(7, 29, dtype=torch.int16)
    kernel.launch(logits, out)
    _, best = reference(logits, (7, 29))
    assert torch.equal(out.long(), best)
    assert (out == 280).any() and not (out == 290).any()


def test_fused_kernel_lets_nan_win_as_argmax_does(kernel):
    logits = torch.randn(1, 6, 3, 3, generator=torch.Generator().manual_seed(2))
    logits[0, 4, 1, 1] = float("nan")  # a broken logit must show, not hide behind the other classes
    out = torch.zeros(12, 12, dtype=torch.uint8)
    counts = kernel.launch(logits, out).view(3, 3)
    up, best = reference(logits, (12, 12))
    nan = up.isnan().any(0)
    assert nan.any() and (out[nan] == 4).all()
    assert torch.equal(out[~nan].long(), best[~nan])
    # the four cells with the NaN among their corners search every class; the others prune
    assert (counts[0:2, 0:2] == -1).all() and (counts >= 0).sum() == 9 - 4


def smooth_logits(k: int, size: tuple[int, int], seed: int) -> torch.Tensor:
    """Logits that change slowly over the token grid, as a trained head's do: a few classes near any token."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.randn(1, k, 2, 3, generator=g) * 4
    return F.interpolate(coarse, size=size, mode="bilinear", align_corners=False) + 0.05 * torch.randn(
        1, k, *size, generator=g
    )


def test_candidate_classes_are_few_where_logits_are_smooth_and_change_nothing(kernel):
    logits = smooth_logits(24, (4, 6), seed=3)
    out, every = torch.empty(16, 24, dtype=torch.uint8), torch.empty(16, 24, dtype=torch.uint8)
    counts = kernel.launch(logits, out)
    kernel.launch(logits, every, max_candidates=0)  # every class for every pixel
    assert torch.equal(out, every)
    assert (counts >= 1).all() and counts.float().median() <= 3, counts
    up, best = reference(logits, (16, 24))
    assert_argmax_of(out, up, best)


def test_a_cell_with_more_candidates_than_kept_searches_every_class(kernel):
    logits = torch.randn(1, 12, 3, 4, generator=torch.Generator().manual_seed(4))  # noise: many candidates
    out, every = torch.empty(9, 11, dtype=torch.uint8), torch.empty(9, 11, dtype=torch.uint8)
    counts = kernel.launch(logits, out, max_candidates=2)
    kernel.launch(logits, every, max_candidates=0)
    assert (counts == -1).any() and (counts > 0).any()
    assert torch.equal(out, every)


# a plain launch passes Python floats as fp32, inductor as fp64
@pytest.mark.parametrize("scale", ["fp32", "fp64"])
@pytest.mark.parametrize(("src", "dst"), [("*fp16", "*u8"), ("*bf16", "*u8"), ("*fp32", "*i16")])
def test_fused_kernels_compile_for_a_gpu_from_every_logit_and_class_type(src, dst, scale):
    # Triton's compiler runs without a GPU: type errors that its CPU interpreter lets pass fail here, not on a robot
    triton = pytest.importorskip("triton")
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    from vpengine.models import _triton_upsample_argmax as module

    ints = {"K": "i32", "h": "i32", "w": "i32"}
    kernels = {
        module._candidates_kernel: (
            {"src": src, "cand": "*i32", "count": "*i32", **ints, "MAX_CAND": "constexpr", "CLASS_BLOCK": "constexpr"},
            {"MAX_CAND": module.MAX_CANDIDATES, "CLASS_BLOCK": module.CLASS_BLOCK},
        ),
        module._upsample_argmax_kernel: (
            {"src": src, "dst": dst, "cand": "*i32", "count": "*i32", **ints, "H": "i32", "W": "i32", "scale_h": scale,
             "scale_w": scale, "MAX_CAND": "constexpr", "BLOCK": "constexpr"},
            {"MAX_CAND": module.MAX_CANDIDATES, "BLOCK": module.BLOCK},
        ),
    }  # fmt: skip
    for fn, (signature, constants) in kernels.items():
        source = ASTSource(fn=fn, signature=signature, constexprs=constants)
        compiled = triton.compile(source, target=GPUTarget("cuda", 90, 32))  # an H100's architecture
        assert compiled.asm["cubin"], fn.__name__
