"""The Faster R-CNN head's static path (Note [Static detection]) equals torchvision's (``forward_reference``) in
float32 on the CPU: the same labels and counts, boxes within 0.5 px, scores within 1e-3, for batches of several
frames of several sizes, on spread-out random weights and on weights after a few training steps."""

from __future__ import annotations

import pytest
import torch

from helpers import detection
from vpengine.models import detection_static
from vpengine.models.detection_static import candidates_per_proposal

FRAMES = [((120, 180), (8, 12)), ((140, 140), (10, 10)), ((90, 240), (6, 15))]  # input frame, token grid
OPTIONS = {
    "defaults": {},
    # few proposals per level, fewer after NMS than the post-NMS cap: padded proposal slots
    "few proposals": {"rpn_score_threshold": 0.5, "rpn_pre_nms_top_n_test": 10, "rpn_post_nms_top_n_test": 60},
    # every class of every proposal is a candidate, most of them suppressed
    "no threshold": {"score_threshold": 0.0, "max_detections": 1000, "nms_threshold": 0.3},
    "low threshold": {"score_threshold": 0.05, "max_detections": 20, "min_size": 3.0},
}


def run_both(head, x):
    with torch.inference_mode():
        return head({"patch.3": x}), head.forward_reference({"patch.3": x})


def assert_meaningful(want, what):
    """Detections in most frames, and no tied scores (so NMS order is not a coin toss)."""
    counts = want["count"].tolist()
    assert sum(c > 0 for c in counts) >= len(counts) // 2, f"{what}: counts {counts}"
    for i, n in enumerate(counts):
        assert len(set(want["scores"][i, :n].tolist())) == n, f"{what}, frame {i}: tied scores"


@pytest.mark.parametrize("options", list(OPTIONS), ids=list(OPTIONS))
@pytest.mark.parametrize(("frame", "grid"), FRAMES, ids=[f"{f[0]}x{f[1]}" for f, _ in FRAMES])
def test_static_path_equals_torchvision_on_spread_random_weights(frame, grid, options):
    head = detection.spread_(detection.build(frame, grid, OPTIONS[options]))
    x = detection.tokens(head, 4, seed=sum(frame))
    got, want = run_both(head, x)
    assert_meaningful(want, options)
    detection.assert_same_detections(got, want, f"{options}, {frame}")
    if options == "few proposals":
        with torch.inference_mode():
            _, valid = detection_static.proposals(head, head.feature_maps(x))
        # 10 per level of 4 levels: 40 proposal slots, not all of them filled
        assert valid.shape[1] == 40 and (valid.sum(1) < 40).all(), valid.sum(1)


@pytest.fixture(scope="module")
def trained_state():
    """Weights after a few epochs of `vpengine train detector`'s optimisation, shared by every frame size."""
    frame, grid = FRAMES[0]
    return detection.train_(detection.build(frame, grid), epochs=2).state_dict()


@pytest.mark.parametrize(("frame", "grid"), FRAMES, ids=[f"{f[0]}x{f[1]}" for f, _ in FRAMES])
def test_static_path_equals_torchvision_on_trained_weights(trained_state, frame, grid):
    head = detection.build(frame, grid, {"score_threshold": 0.05})
    head.load_state_dict(trained_state)
    x = detection.tokens(head, 4, seed=7)
    got, want = run_both(head, x)
    assert_meaningful(want, "trained")
    detection.assert_same_detections(got, want, f"trained, {frame}")


def test_a_frame_in_a_batch_gets_what_it_gets_alone():
    head = detection.spread_(detection.build(*FRAMES[0]))
    x = detection.tokens(head, 3, seed=1)
    with torch.inference_mode():
        batch = head({"patch.3": x})
        for i in range(3):
            alone = head({"patch.3": x[i : i + 1]})
            detection.assert_same_detections(alone, {k: v[i : i + 1] for k, v in batch.items()}, f"frame {i}")


def test_static_path_traces_whole_without_host_syncs():
    # fullgraph: dynamo fails on any graph break, which .item(), nonzero or a data-dependent shape would force
    head = detection.spread_(detection.build(*FRAMES[0], {"score_threshold": 0.2}))
    x = detection.tokens(head, 2, seed=3)
    compiled = torch.compile(head, fullgraph=True, dynamic=False, backend="aot_eager")
    with torch.inference_mode():
        got, want = compiled({"patch.3": x}), head.forward_reference({"patch.3": x})
    detection.assert_same_detections(got, want, "compiled")


@pytest.mark.parametrize(
    ("classes", "threshold", "bound"), [(80, 0.5, 2), (80, 0.3, 3), (80, 0.05, 20), (3, 0.05, 3), (80, 0.0, 80)]
)
def test_candidates_per_proposal_bounds_the_classes_above_the_threshold(classes, threshold, bound):
    assert candidates_per_proposal(classes, threshold) == bound
    # the bound holds for the worst softmax: as many classes as possible just above the threshold
    n = min(classes, int(1 / threshold) if threshold else classes)
    logits = torch.full((classes + 1,), -30.0)
    logits[1 : n + 1] = 0.0
    assert int((logits.softmax(0)[1:] > threshold).sum()) <= bound
