"""The Faster R-CNN head's static path on CUDA (Note [Static detection], Note [Exact static NMS]): the Triton NMS
against torchvision's, the head against torchvision's path, no host sync, and the compile backend capturing it in one
CUDA graph per batch size. Run on the GPU machine: ``pytest -m gpu tests/gpu/test_detection_cuda.py``."""

from __future__ import annotations

import pytest
import torch

from helpers import detection
from helpers.detection import crowded, static_keep, torchvision_keep
from vpengine.backends import make_executor
from vpengine.bench.common import event_ms
from vpengine.models.nms import greedy_nms

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.timeout(900),
    pytest.mark.usefixtures("require_cuda", "inductor_in_process"),
]

CUDA = "cuda"
FRAMES = [((120, 180), (8, 12)), ((90, 240), (6, 15)), ((1080, 1920), (37, 66))]  # 37x66: ViT-S/14 on 1080p
IDS = [f"{f[0]}x{f[1]}" for f, _ in FRAMES]


def to_cuda(*xs: torch.Tensor) -> list[torch.Tensor]:
    return [x.to(CUDA) for x in xs]


@pytest.mark.parametrize("threshold", [0.3, 0.5, 0.7])
@pytest.mark.parametrize("t", [1, 33, 1000, 4000])
def test_triton_nms_keeps_what_batched_nms_keeps_on_the_cpu(t, threshold):
    # The reference is torchvision on the CPU, whose sort keeps tied scores in their order, as the head's stable
    # sort does. Its CUDA nms sorts without that promise, so with these ties it need not agree even with itself on
    # the CPU: it is no reference here.
    boxes, scores, labels, valid = crowded(4, t, seed=t)
    want = torchvision_keep(boxes, scores, labels, valid, threshold)
    assert static_keep(greedy_nms, *to_cuda(boxes, scores, labels, valid), threshold) == want


@pytest.fixture(scope="module")
def trained_state():
    frame, grid = FRAMES[0]
    return detection.train_(detection.build(frame, grid), epochs=2).state_dict()


def heads_for(frame, grid, weights, trained_state, options=None):
    """The same head twice on CUDA: one for the path under test, one for torchvision's path as the reference."""
    made = []
    for _ in range(2):
        head = detection.build(frame, grid, options, device=CUDA)
        if weights == "trained":
            head.load_state_dict(trained_state)
        else:
            detection.spread_(head)
        made.append(head)
    return made


@pytest.mark.parametrize("weights", ["spread", "trained"])
@pytest.mark.parametrize(("frame", "grid"), FRAMES, ids=IDS)
def test_static_path_on_cuda_equals_torchvision_and_never_syncs(frame, grid, weights, trained_state):
    head, _ = heads_for(frame, grid, weights, trained_state, {"score_threshold": 0.05})
    x = detection.tokens(head, 4, seed=sum(frame), device=CUDA)
    with torch.inference_mode():
        want = head.forward_reference({"patch.3": x})
        head({"patch.3": x})  # anchors are computed on the first call, then cached
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")
        try:
            got = head({"patch.3": x})
        finally:
            torch.cuda.set_sync_debug_mode("default")
    assert int(want["count"].sum()) > 0
    detection.assert_same_detections(got, want, f"{weights}, {frame}")


@pytest.mark.parametrize("weights", ["spread", "trained"])
@pytest.mark.parametrize(("frame", "grid"), FRAMES[::2], ids=IDS[::2])  # a small grid and 1080p: each compiles
def test_compiled_static_path_is_one_cuda_graph_per_batch_size_and_equals_torchvision(
    frame, grid, weights, trained_state
):
    head, reference = heads_for(frame, grid, weights, trained_state, {"score_threshold": 0.05})
    # the compile backend's defaults: fullgraph (a graph break fails warm-up) and CUDA graphs; two batch sizes show
    # a graph each (a compile each, tens of seconds cold on one compile thread)
    ex = make_executor(head, "compile", CUDA, "det", max_batch=2)
    assert ex.describe()["cudagraphs"] and ex.describe()["fullgraph"]
    for b in (1, 2):
        x = detection.tokens(reference, b, seed=b, device=CUDA)
        torch.cuda.set_sync_debug_mode("error")
        try:
            got = {k: v.clone() for k, v in ex({"patch.3": x}).items()}
        finally:
            torch.cuda.set_sync_debug_mode("default")
        with torch.inference_mode():
            want = reference.forward_reference({"patch.3": x})
        detection.assert_same_detections(got, want, f"{weights}, {frame}, batch of {b}")


@pytest.fixture(scope="module")
def lite_paths():
    """frcnn_dinov2_lite as the shipped GPU config runs it (ViT-S features of 1080p frames, 80 classes, fp16), once
    for every batch size below: torchvision's eager path and the compiled static path (batches 1-8, minutes cold)."""
    import torch._inductor.config as inductor_config

    from helpers import heads

    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    grid, dim = (37, 66), 384
    cfg = heads.head_config(
        (1080, 1920), {"name": "det", "model": "frcnn_dinov2_lite", "options": {"num_classes": 80}}, device=CUDA
    )
    torchvision_path = heads.build_head(cfg, grid, dim, CUDA)
    torchvision_path.forward = torchvision_path.forward_reference  # what the head ran before the static path
    slow = make_executor(torchvision_path, "eager", CUDA, "det", precision="fp16")
    with inductor_config.patch(compile_threads=1):  # as the inductor_in_process fixture: no pool left behind
        fast = make_executor(
            heads.build_head(cfg, grid, dim, CUDA), "compile", CUDA, "det", precision="fp16", max_batch=8
        )
    return slow, fast, grid, dim


@pytest.mark.parametrize("batch", [1, 4, 8])
def test_lite_recipe_at_1080p_compiled_is_faster_than_torchvision_eager(batch, lite_paths):
    """Device time of the compiled static path against torchvision's eager path, printed for the results."""
    slow, fast, grid, dim = lite_paths
    x = {"patch.3": torch.randn(batch, grid[0] * grid[1], dim, device=CUDA)}  # the features mailbox: float32
    slow_ms = event_ms(lambda: slow(x), 20, warmup=3)
    fast_ms = event_ms(lambda: fast(x), 50, warmup=5)
    print(
        f"frcnn_dinov2_lite, batch {batch}, 1080p: torchvision eager {slow_ms:.2f} ms, static compiled {fast_ms:.2f} ms"
    )
    assert fast_ms < slow_ms
