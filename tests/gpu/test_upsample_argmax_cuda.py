"""The fused upsample + argmax of the linear segmentation head on CUDA (Note [Fused upsample + argmax]): the kernel
compiled for the GPU against float64 PyTorch at 1080p, the head choosing it, compiled into a CUDA graph, and faster
than the PyTorch path it replaces. Run on the GPU machine: ``pytest -m gpu tests/gpu``."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from helpers import heads
from helpers.classmaps import assert_argmax_of, reference
from vpengine.backends import make_executor
from vpengine.bench.common import event_ms
from vpengine.models.upsample_argmax import fused_unavailable, fused_upsample_argmax

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.timeout(600),
    pytest.mark.usefixtures("require_cuda", "inductor_in_process"),
]

CUDA = torch.device("cuda")
FRAME = (1080, 1920)
GRID = (37, 66)  # dinov2_vits14's token grid for a 1080p frame
DIM = 384


@pytest.fixture(autouse=True)
def fused_kernel_available() -> None:
    # Triton comes with PyTorch's CUDA wheels; this also registers the op
    assert fused_unavailable(CUDA) is None


def build_seg(upsample: str, precision: str = "fp16"):
    head = {"name": "seg", "model": "dinov2_linear_ade20k_s", "options": {"upsample": upsample}}
    cfg = heads.head_config(FRAME, head, device="cuda", precision=precision)
    return heads.build_head(cfg, GRID, DIM, "cuda", "float16" if precision == "fp16" else "float32")


def features(seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator(device=CUDA).manual_seed(seed)
    return {"patch.3": torch.randn(1, GRID[0] * GRID[1], DIM, generator=g, device=CUDA).half()}


def tolerance(logits: torch.Tensor) -> float:
    """How far float32 interpolation (PyTorch's and the kernel's) may be from float64: source coordinates up to
    the grid's size carry float32 rounding into the weights, which scale the logits' range."""
    spread = (logits.max() - logits.min()).item()
    return 2e-7 * max(logits.shape[-2:]) * spread


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16], ids=str)
@pytest.mark.parametrize("classes", [150, 21])
def test_fused_kernel_on_cuda_is_the_argmax_of_float64_upsampling_at_1080p(dtype, classes):
    g = torch.Generator(device=CUDA).manual_seed(classes)
    logits = (torch.randn(1, classes, *GRID, generator=g, device=CUDA) * 3).to(dtype)
    got = fused_upsample_argmax(logits, FRAME, torch.uint8)
    assert got.dtype == torch.uint8 and got.shape == (1, *FRAME) and got.is_cuda
    got = got[0]  # the batch of one
    up, best = reference(logits, FRAME)  # float64 of the same (rounded) logits
    share = assert_argmax_of(got, up, best, tol=tolerance(logits), at_most=1e-5)
    print(f"{classes} classes, {dtype}: {share:.2e} of pixels at a near-tie differ")


def test_a_batch_is_one_launch_of_each_kernel_and_each_frame_its_own_map():
    # the frame is the grids' last axis (Note [Fused upsample + argmax]): each frame as if it were alone
    g = torch.Generator(device=CUDA).manual_seed(3)
    logits = (torch.randn(3, 150, *GRID, generator=g, device=CUDA) * 3).half()
    got = fused_upsample_argmax(logits, FRAME, torch.uint8)
    assert got.shape == (3, *FRAME)
    for i in range(3):
        assert torch.equal(got[i], fused_upsample_argmax(logits[i : i + 1], FRAME, torch.uint8)[0]), i
    assert not torch.equal(got[0], got[1])


def test_candidate_classes_on_smooth_logits_give_the_same_map_faster():
    # A trained head's logits change slowly from token to token: each cell keeps a few candidate classes
    from vpengine.models import _triton_upsample_argmax as kernel

    g = torch.Generator(device=CUDA).manual_seed(7)
    coarse = torch.randn(1, 150, 4, 7, generator=g, device=CUDA) * 4
    fine = F.interpolate(coarse, size=GRID, mode="bilinear", align_corners=False)
    logits = (fine + 0.05 * torch.randn(fine.shape, generator=g, device=CUDA)).half()
    out, every = (torch.empty(FRAME, dtype=torch.uint8, device=CUDA) for _ in range(2))
    counts = kernel.launch(logits, out)
    kernel.launch(logits, every, max_candidates=0)
    assert torch.equal(out, every)
    assert (counts >= 1).all() and counts.float().median().item() <= 4
    up, best = reference(logits, FRAME)
    assert_argmax_of(out, up, best, tol=tolerance(logits), at_most=1e-5)
    fast = _median_ms(lambda: kernel.launch(logits, out))
    slow = _median_ms(lambda: kernel.launch(logits, every, max_candidates=0))
    print(f"smooth logits, 150 classes at 1080p: {fast:.3f} ms with candidates, {slow:.3f} ms searching every class")
    assert fast < 0.5 * slow, (fast, slow)


def test_the_head_runs_the_fused_kernel_on_cuda_and_agrees_with_the_pytorch_path():
    fused, plain = build_seg("auto"), build_seg("torch")
    assert (fused.upsample, plain.upsample) == ("fused", "torch")
    plain.load_state_dict(fused.state_dict())
    x = features()
    with torch.inference_mode():
        logits = fused.logits(x)
        got = fused(x)["classes"][0]  # the batch of one
        old = plain(x)["classes"][0]
    assert got.dtype == old.dtype == torch.uint8 and got.shape == old.shape == FRAME
    up, best = reference(logits, FRAME)
    assert_argmax_of(got, up, best, tol=tolerance(logits), at_most=1e-5)
    # PyTorch's eager path rounds the upsampled float16 logits before its argmax: near-ties at that rounding differ
    differ = (got != old).float().mean().item()
    assert differ <= 2e-3, f"{differ:.3%} of pixels differ from the PyTorch path"
    assert len(got.unique()) > 10


def _median_ms(fn) -> float:  # type: ignore[no-untyped-def]
    return event_ms(fn, 200, warmup=10)


def test_compiled_head_captures_the_fused_kernel_in_its_cuda_graph_and_is_faster_even_on_noise():
    fused, plain = build_seg("auto"), build_seg("torch")
    plain.load_state_dict(fused.state_dict())
    x = features(1)
    with torch.inference_mode():
        want = fused(x)["classes"].clone()
    fast = make_executor(fused, "compile", CUDA, "seg", precision="fp16")
    slow = make_executor(plain, "compile", CUDA, "seg", precision="fp16")
    assert fast.describe()["cudagraphs"] and slow.describe()["cudagraphs"]
    got = fast(x)["classes"]
    assert got.dtype == torch.uint8
    differ = (got != want).float().mean().item()
    assert differ <= 1e-4, f"{differ:.3%} of pixels differ between the compiled and the eager fused head"
    before = torch.cuda.memory_allocated()
    fast_ms, slow_ms = _median_ms(lambda: fast(x)), _median_ms(lambda: slow(x))
    assert torch.cuda.memory_allocated() == before  # replays allocate nothing
    print(f"seg head at 1080p, compiled + CUDA graph: fused {fast_ms:.3f} ms, PyTorch path {slow_ms:.3f} ms")
    # Random features and weights give noise-like logits, the kernel's worst case (most cells search every class):
    # 0.68 against 0.93 ms on an H100 (0.52 before candidate classes); smooth logits: the candidate test above
    assert fast_ms < slow_ms, (fast_ms, slow_ms)
