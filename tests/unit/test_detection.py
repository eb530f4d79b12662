"""Faster R-CNN head on foundation-model features: specs, coordinates, capacity, checkpoints (no processes)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from vpengine.config import load_config
from vpengine.models import detection_static
from vpengine.models.base import BuildContext, ModelBuildError, check_outputs
from vpengine.models.build import build_model
from vpengine.models.detection import FasterRCNNHead
from vpengine.models.preprocess import ImagePreprocess
from vpengine.models.weights import CheckpointError
from vpengine.runtime.plan import make_plan
from vpengine.specs import TensorSpec

# Small enough to build and run in milliseconds; the layout is the full recipe's.
SMALL = {"num_classes": 3, "out_channels": 16, "representation_size": 32, "rpn_post_nms_top_n_test": 300}


def config(
    options: dict | None = None,
    *,
    height: int = 120,
    width: int = 160,
    resize: str = "aspect",
    size: int = 112,
    checkpoint: str | None = None,
    model: str = "frcnn_dinov2",
    base: dict | None = SMALL,
):
    return load_config(
        {
            "mode": "thread",
            "input": {"height": height, "width": width},
            "foundation_model": {"model": "tiny_vit", "preprocess": {"resize": resize, "size": size}},
            "heads": [
                {
                    "name": "det",
                    "model": model,
                    "checkpoint": checkpoint,
                    "options": {**(base or {}), **(options or {})},
                }
            ],
            "weights": {"random_weights": checkpoint is None},
        }
    )


def build(cfg) -> tuple[object, FasterRCNNHead]:
    plan = make_plan(cfg)
    head = build_model(cfg, "det", "head", plan.features, plan.feature_meta, torch.device("cpu"), False)
    assert isinstance(head, FasterRCNNHead)
    return plan, head


def tokens_of(plan, seed: int = 0) -> torch.Tensor:
    """patch.3 of the tiny backbone for a random frame (real features, not noise), as a batch of one."""
    cfg = plan.cfg
    fm = build_model(cfg, "foundation", "foundation", plan.frame_spec, {}, torch.device("cpu"), False)
    g = torch.Generator().manual_seed(seed)
    frame = torch.randint(0, 256, plan.frame_spec["frame"].shape, generator=g, dtype=torch.uint8)
    with torch.inference_mode():
        return fm({"frame": frame[None]})["patch.3"]


def force_class(head: FasterRCNNHead, label: int) -> None:
    """Make the box head return its proposals unchanged, all of class ``label`` with a high, varying score."""
    pred = head.roi_heads.box_predictor
    with torch.no_grad():
        pred.bbox_pred.weight.zero_()
        pred.bbox_pred.bias.zero_()
        pred.cls_score.weight.mul_(0.01)  # scores still differ a little from RoI to RoI
        pred.cls_score.bias.zero_()
        pred.cls_score.bias[label + 1] = 6.0  # +1: torchvision's label 0 is background


def test_plan_declares_fixed_capacity_outputs_and_detection_meta():
    plan = make_plan(config({"class_names": ["person", "car", "dog"], "max_detections": 7}))
    head = plan.heads["det"]
    assert head.output_spec == {
        "boxes": TensorSpec((7, 4), "float32"),
        "scores": TensorSpec((7,), "float32"),
        "labels": TensorSpec((7,), "int32"),
        "count": TensorSpec((), "int32"),
    }
    assert head.input_spec == {"patch.3": plan.features["patch.3"]}
    assert head.meta["kind"] == "detection" and head.meta["labels"] == ["person", "car", "dog"]
    assert head.meta["max_detections"] == 7
    assert all(p.device.type == "meta" for p in head.parameters())
    # stride-14 tokens: levels at 7, 14, 28 pixels and the pooled one at 56
    assert head.meta["pyramid"] == {"up2": 7.0, "same": 14.0, "down2": 28.0, "pool": 56.0}


def test_outputs_match_specs_with_padding_past_count_and_best_first():
    plan, head = build(config({"score_threshold": 0.0, "max_detections": 50}))
    with torch.inference_mode():
        out = head({"patch.3": tokens_of(plan)})
    check_outputs("det", plan.heads["det"].output_spec, out, batch=1)
    out = {k: v[0] for k, v in out.items()}
    n = int(out["count"])
    assert 1 < n <= 50
    boxes, scores, labels = out["boxes"], out["scores"], out["labels"]
    assert torch.all(boxes[:n, 2:] > boxes[:n, :2])
    assert torch.all(boxes[:n, 0::2] <= 160) and torch.all(boxes[:n, 1::2] <= 120) and torch.all(boxes[:n] >= 0)
    assert torch.all(scores[:n] > 0) and torch.all(scores[:n].diff() <= 0)
    assert torch.all((labels[:n] >= 0) & (labels[:n] < 3))
    assert torch.all(boxes[n:] == 0) and torch.all(scores[n:] == 0) and torch.all(labels[n:] == -1)
    fin = head.finalize({k: v.numpy() for k, v in out.items()})
    assert fin["count"] == n and fin["boxes"].shape == (n, 4) and fin["labels"].shape == (n,)
    np.testing.assert_array_equal(fin["scores"], scores[:n].numpy())


def _extent_in_image(pre: ImagePreprocess, frame: np.ndarray) -> list[float]:
    """Where the bright region of ``frame`` lands in the preprocessed image, measured on the pixels."""
    with torch.inference_mode():
        img = pre({"frame": torch.from_numpy(frame)[None]})["image"][0, 0]
    mask = img > (img.max() + img.min()) / 2
    ys, xs = torch.nonzero(mask, as_tuple=True)
    return [float(xs.min()), float(ys.min()), float(xs.max()) + 1, float(ys.max()) + 1]


@pytest.mark.parametrize("resize", ["aspect", "square", "none"])
def test_hand_made_proposal_over_a_known_region_of_a_2to1_frame_maps_back_to_input_pixels(resize):
    h, w = (
        100,
        200,
    )  # 2:1; `square` squashes it to 56x56, `aspect` scales it to 56x112, `none` crops to 98x196
    region = [120.0, 20.0, 180.0, 80.0]  # x1, y1, x2, y2 of a bright block, input pixels
    cfg = config({"score_threshold": 0.5}, height=h, width=w, resize=resize, size=56)
    plan, head = build(cfg)
    force_class(head, label=2)
    frame = np.zeros((h, w, 3), np.uint8)
    frame[20:80, 120:180] = 255
    pre = ImagePreprocess(h, w, cfg.foundation_model.preprocess, 14, "bgr", "uint8")
    assert tuple(pre.size) == tuple(plan.feature_meta["image_size"])
    proposal = torch.tensor([_extent_in_image(pre, frame)])
    with torch.inference_mode():
        (det,) = head.predict(tokens_of(plan), proposals=[proposal])
    assert det["boxes"].shape == (1, 4) and det["labels"].tolist() == [2]
    # one preprocessed pixel, in input pixels: how precisely the block's edge can be measured after resizing
    tol = max(w / pre.size[1], h / pre.size[0]) if resize != "none" else 0.0
    np.testing.assert_allclose(det["boxes"][0].numpy(), region, atol=tol + 1e-4)
    torch.testing.assert_close(head.boxes_to_image(det["boxes"]), proposal)


def test_low_precision_head_keeps_box_geometry_in_float32():
    # A backend runs the head cast to bf16 under autocast (Note [Precision] in backends/base.py). bf16 has 8
    # mantissa bits: coordinates in it would land on a 0.5-pixel grid above 64, a whole pixel above 128.
    h, w = 100, 200
    plan, head = build(config({"score_threshold": 0.5}, height=h, width=w, resize="square", size=112))
    force_class(head, label=0)
    head.to(torch.bfloat16)
    proposal = torch.tensor([[10.3, 20.7, 100.9, 60.1]])  # preprocessed pixels, none of them on a bf16 grid
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
        (det,) = head.predict(tokens_of(plan).to(torch.bfloat16), proposals=[proposal])
    ih, iw = plan.feature_meta["image_size"]
    expected = proposal * torch.tensor([w / iw, h / ih, w / iw, h / ih])
    assert det["boxes"].dtype == torch.float32 and det["labels"].tolist() == [0]
    torch.testing.assert_close(det["boxes"], expected, rtol=0, atol=1e-3)


@pytest.mark.parametrize(
    ("box", "level"),
    [([70.0, 20.0, 140.0, 90.0], "up2"), ([100.0, 50.0, 400.0, 250.0], "same")],
)
def test_roi_pooling_and_anchors_follow_the_exact_stride_14_geometry(box, level):
    # Token j of a stride-14 ViT covers pixels [14j, 14j + 14). Fill every level with the image coordinates of
    # its cells' centres: whatever RoIAlign samples inside a box must then average to the box centre.
    plan, head = build(config(height=280, width=560, size=280))  # 280x560 -> 20x40 tokens
    stride = dict(head.meta["pyramid"])
    maps = {}
    for name, m in head.feature_maps(tokens_of(plan)).items():
        s = stride[name]
        ys, xs = torch.meshgrid(torch.arange(m.shape[-2]), torch.arange(m.shape[-1]), indexing="ij")
        m = torch.zeros_like(m)
        m[0, 0], m[0, 1] = (xs + 0.5) * s, (ys + 0.5) * s
        maps[name] = m
    pooled = head.roi_heads.box_roi_pool(maps, [torch.tensor([box])], [head.image_hw])
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    # MultiScaleRoIAlign samples with aligned=False (torchvision's convention): half a cell to the right/down.
    s = stride[level]
    assert float(pooled[0, 0].mean()) == pytest.approx(cx + s / 2, abs=0.5)
    assert float(pooled[0, 1].mean()) == pytest.approx(cy + s / 2, abs=0.5)

    anchors = head.rpn.anchor_generator(head._images(1, torch.device("cpu")), list(maps.values()))[0]
    a = head.rpn.anchor_generator.num_anchors_per_location()[0]
    start = 0
    for name, m in maps.items():
        n = m.shape[-2] * m.shape[-1] * a
        centres = ((anchors[start : start + n, :2] + anchors[start : start + n, 2:]) / 2).unique(dim=0)
        start += n
        xs = sorted(set(centres[:, 0].tolist()))
        assert xs == pytest.approx([(j + 0.5) * stride[name] for j in range(m.shape[-1])]), name
    assert start == anchors.shape[0]


def test_count_never_exceeds_capacity_and_keeps_the_best():
    # score 0 and no NMS: every class of every proposal passes, hundreds of candidates
    opts = {"score_threshold": 0.0, "nms_threshold": 1.0, "min_size": 0.0}
    plan, small = build(config({**opts, "max_detections": 5}))
    _, large = build(config({**opts, "max_detections": 1000}))  # same seed: same weights
    tokens = tokens_of(plan)
    with torch.inference_mode():
        out = {k: v[0] for k, v in small({"patch.3": tokens}).items()}
        (everything,) = large.predict(tokens)
    assert everything["scores"].shape[0] > 50
    assert int(out["count"]) == 5
    torch.testing.assert_close(out["scores"], everything["scores"][:5])
    torch.testing.assert_close(out["boxes"], everything["boxes"][:5])


@pytest.mark.parametrize("path", ["static", "torchvision"])
def test_several_objects_give_several_detections_in_the_padded_output(monkeypatch, path):
    plan, head = build(config({"max_detections": 6}))
    force_class(head, label=1)
    props = torch.tensor([[10.0, 10.0, 40.0, 40.0], [60.0, 20.0, 100.0, 90.0], [110.0, 50.0, 150.0, 100.0]])
    if path == "static":  # the proposal stage's fixed-size answer: 4 slots, the last one padding
        padded = (torch.cat([props, torch.tensor([[0.0, 0.0, 50.0, 50.0]])])[None], torch.tensor([[1, 1, 1, 0]]) > 0)
        monkeypatch.setattr(detection_static, "proposals", lambda head, maps: padded)
        run = head
    else:
        monkeypatch.setattr(head.rpn, "forward", lambda images, features, targets=None: ([props], {}))
        run = head.forward_reference
    with torch.inference_mode():
        out = {k: v[0] for k, v in run({"patch.3": tokens_of(plan)}).items()}
    assert int(out["count"]) == 3
    found = sorted(map(tuple, out["boxes"][:3].tolist()))
    expected = sorted(map(tuple, head.boxes_to_input(props).tolist()))
    np.testing.assert_allclose(found, expected, atol=1e-3)
    assert out["labels"].tolist() == [1, 1, 1, -1, -1, -1]
    assert torch.all(out["scores"][:3] > 0.5) and torch.all(out["scores"][:3].diff() <= 0)
    assert torch.all(out["boxes"][3:] == 0) and torch.all(out["scores"][3:] == 0)


def test_state_dict_has_torchvision_faster_rcnn_layout():
    from torch import nn
    from torchvision.models.detection import FasterRCNN
    from torchvision.models.detection.anchor_utils import AnchorGenerator

    one_size_per_level = [[32], [64], [128], [256]]  # torchvision's FPN default: 3 anchors per location
    _, head = build(
        config(
            {
                "out_channels": 256,
                "representation_size": 1024,
                "num_classes": 90,
                "rpn_anchor_sizes": one_size_per_level,
            }
        )
    )
    backbone = nn.Conv2d(3, 256, 1)
    backbone.out_channels = 256  # what FasterRCNN asks of a backbone
    tv = FasterRCNN(backbone, num_classes=91, rpn_anchor_generator=AnchorGenerator(((32,),), ((0.5, 1.0, 2.0),)))
    tv_sd = {k: v for k, v in tv.state_dict().items() if not k.startswith("backbone.")}
    ours = head.state_dict()
    assert {k for k in ours if not k.startswith("pyramid.")} == set(tv_sd)
    # so the RPN and box head of a torchvision model load as they are, next to the pyramid's own keys
    from vpengine.models.weights import apply_state_dict

    apply_state_dict(head, {**tv_sd, **{k: v for k, v in ours.items() if k.startswith("pyramid.")}}, "tv", "test")
    key = "roi_heads.box_predictor.cls_score.weight"
    torch.testing.assert_close(head.state_dict()[key], tv_sd[key])


def test_random_weights_depend_only_on_the_seed_option():
    # In thread mode other models are built concurrently and draw from the global RNG: it must not matter.
    torch.manual_seed(1)
    _, a = build(config({"seed": 3}))
    torch.manual_seed(2)
    torch.rand(1000)
    _, b = build(config({"seed": 3}))
    _, c = build(config({"seed": 4}))
    for k, v in a.state_dict().items():
        assert torch.equal(v, b.state_dict()[k]), k
    differ = [k for k, v in a.state_dict().items() if not torch.equal(v, c.state_dict()[k])]
    # every weight is drawn from the seed (norm layers start at 1 and 0, biases of the RPN at 0)
    assert set(differ) == {
        k for k in a.state_dict() if not (".norm." in k or (k.startswith("rpn.head.") and k.endswith(".bias")))
    }


@pytest.mark.parametrize("suffix", [".pth", ".safetensors"])
def test_random_weights_state_dict_loads_strictly_from_a_file(tmp_path, suffix):
    _, src = build(config({"seed": 7}))
    sd = {k: v.clone() for k, v in src.state_dict().items()}
    path = tmp_path / f"head{suffix}"
    if suffix == ".safetensors":
        from safetensors.torch import save_file

        save_file(sd, str(path))
    else:
        torch.save(sd, str(path))
    _, loaded = build(config({"seed": 0}, checkpoint=str(path)))
    _, fresh = build(config({"seed": 0}))
    assert not torch.equal(fresh.state_dict()["rpn.head.cls_logits.weight"], sd["rpn.head.cls_logits.weight"])
    for k, v in loaded.state_dict().items():
        assert torch.equal(v, sd[k]), k


def test_legacy_torchvision_rpn_conv_keys_are_accepted(tmp_path):
    _, src = build(config())
    sd = src.state_dict()
    for s in ("weight", "bias"):
        sd[f"rpn.head.conv.{s}"] = sd.pop(f"rpn.head.conv.0.0.{s}")
    torch.save(sd, tmp_path / "old.pth")
    _, loaded = build(config(checkpoint=str(tmp_path / "old.pth")))
    assert torch.equal(loaded.rpn.head.conv[0][0].weight, sd["rpn.head.conv.weight"])


def test_wrong_state_dict_fails_naming_file_and_keys_and_loads_nothing(tmp_path):
    _, other = build(config({"num_classes": 5}))
    wrong_classes = tmp_path / "five_classes.pth"
    torch.save(other.state_dict(), wrong_classes)
    with pytest.raises(CheckpointError) as e:
        build(config(checkpoint=str(wrong_classes)))
    msg = str(e.value)
    assert "five_classes.pth" in msg and "roi_heads.box_predictor.cls_score.weight" in msg and "3 classes" in msg

    # A checkpoint without the pyramid and with a foreign backbone: its RPN and RoI keys would fit, but the file
    # must be refused as a whole. The head's own weights are moved away from the file's first, so a partial copy
    # would show.
    _, head = build(config())
    sd = {k: v.clone() for k, v in head.state_dict().items() if not k.startswith("pyramid.")}
    sd["backbone.body.conv1.weight"] = torch.zeros(1)
    no_pyramid = tmp_path / "no_pyramid.pth"
    torch.save(sd, no_pyramid)
    with torch.no_grad():
        head.rpn.head.cls_logits.weight.add_(1.0)
    before = {k: v.clone() for k, v in head.state_dict().items()}
    cfg = config(checkpoint=str(no_pyramid))
    plan = make_plan(cfg)
    ctx = BuildContext("head", "det", cfg.head("det"), cfg, plan.features, plan.feature_meta, torch.device("cpu"))
    with pytest.raises(CheckpointError, match=r"missing keys: pyramid\..*unexpected keys: backbone\.body"):
        head.load_checkpoint(ctx)
    for k, v in head.state_dict().items():
        assert torch.equal(v, before[k]), k


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"num_classes": None}, "num_classes or class_names"),
        ({"class_names": ["a", "b"]}, "num_classes is 3 but class_names has 2"),
        ({"scales": [1.0, 2.0]}, "fine to coarse"),
        ({"scales": [3.0]}, "from"),
        ({"rpn_anchor_sizes": [[32]]}, "one non-empty list per pyramid level"),
        ({"layer": "patch.9"}, "patch.9"),
        ({"score_treshold": 0.2}, "score_treshold"),
    ],
)
def test_bad_options_fail_at_plan_time_naming_the_problem(options, message):
    with pytest.raises(ModelBuildError, match=message.replace(".", r"\.")):
        make_plan(config(options))


def test_lite_preset_and_user_options_merge():
    plan = make_plan(config({"num_classes": 2, "out_channels": 64}, model="frcnn_dinov2_lite", base=None))
    head = plan.heads["det"]
    assert head.opts.out_channels == 64  # the user's value wins over the preset's
    assert head.opts.representation_size == 512 and head.opts.rpn_post_nms_top_n_test == 300
