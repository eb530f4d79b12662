"""DINOv2 linear segmentation heads: parity with a reference on Hugging Face's Dinov2Model, official checkpoint
layout and strict loading, labels and palettes, specs and planning, the choice of upsampling (test_upsample_argmax.py
tests the upsampling itself)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn
from transformers import Dinov2Config, Dinov2Model

from helpers import heads
from helpers.heads import upstream
from vpengine.config import load_config
from vpengine.models import palettes
from vpengine.models.base import BuildContext, ModelBuildError, check_outputs
from vpengine.models.build import build_model
from vpengine.models.linear_seg import SIZES, LinearSegHead, checkpoint_name
from vpengine.models.weights import CheckpointError
from vpengine.runtime.plan import make_plan
from vpengine.visualize import overlay_segmentation

EMBED = {"s": 384, "b": 768, "l": 1024, "g": 1536}
N_CLASSES = {"ade20k": 150, "voc2012": 21}


# ------------------------------------------------------------------------------------------------ helpers
def head_config(hw, model="dinov2_linear_ade20k_s", options=None, checkpoint=None):
    return heads.head_config(hw, {"name": "seg", "model": model, "options": options or {}}, checkpoint)


def build_head(hw, grid, dim, **kw):
    return heads.build_head(head_config(hw, **kw), grid, dim)


def official_head(dim, n_classes, seed=0, counter=True):
    """A state dict with the keys of dinov2_vit*14_{ade20k,voc2012}_linear_head.pth (mmseg BNHead, linear config:
    BatchNorm over the last layer's C channels, 1x1 conv_seg to the classes), written out independently."""
    g = torch.Generator().manual_seed(seed)
    sd = {
        "decode_head.conv_seg.weight": torch.randn(n_classes, dim, 1, 1, generator=g) * 0.1,
        "decode_head.conv_seg.bias": torch.randn(n_classes, generator=g) * 0.1,
        "decode_head.bn.weight": torch.rand(dim, generator=g) + 0.5,
        "decode_head.bn.bias": torch.randn(dim, generator=g) * 0.1,
        "decode_head.bn.running_mean": torch.randn(dim, generator=g) * 0.1,
        # small variances, as trained BatchNorms have, so that BatchNorm's eps (1e-5) matters in the parity test
        "decode_head.bn.running_var": torch.rand(dim, generator=g) * 0.02 + 0.002,
    }
    if counter:
        sd["decode_head.bn.num_batches_tracked"] = torch.tensor(40000)
    return sd


def save_mmcv(path, sd):
    torch.save({"meta": {"mmseg_version": "0.27.0", "iter": 40000}, "state_dict": sd}, path)


# ------------------------------------------------------------------------------------------- parity with HF
@pytest.mark.parametrize("hw", [(518, 518), (518, 924)], ids=lambda hw: f"{hw[0]}x{hw[1]}")
def test_logits_match_reference_on_hugging_face_dinov2(hw):
    dim, n = 32, 150
    torch.manual_seed(0)
    backbone = Dinov2Model(
        Dinov2Config(
            hidden_size=dim,
            num_hidden_layers=2,
            num_attention_heads=2,
            intermediate_size=2 * dim,
            patch_size=14,
            image_size=518,
        )
    ).eval()
    sd = official_head(dim, n, seed=1)
    # The reference: plain torch modules, loaded by their own names (not vpengine's loader).
    bn, conv = nn.BatchNorm2d(dim).eval(), nn.Conv2d(dim, n, 1)
    bn.load_state_dict({k.split("bn.")[1]: v for k, v in sd.items() if ".bn." in k})
    conv.load_state_dict({k.split("conv_seg.")[1]: v for k, v in sd.items() if "conv_seg" in k})

    grid = (hw[0] // 14, hw[1] // 14)
    head = build_head(hw, grid, dim, options={"size": None, "num_classes": n, "dataset": None})
    head.load_state_dict({k.removeprefix("decode_head."): v for k, v in sd.items()}, strict=True)

    pixels = torch.randn(1, 3, *hw, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        tokens = backbone(pixel_values=pixels).last_hidden_state  # after the final LayerNorm, CLS first
        patch = tokens[:, 1:]
        fmap = patch.reshape(1, *grid, dim).permute(0, 3, 1, 2)
        ref = conv(bn(fmap))
        inputs = {"patch.3": patch}
        ours = head.logits(inputs)
        classes = head(inputs)["classes"]
    assert ours.shape == ref.shape == (1, n, *grid)
    rel = ((ours - ref).abs().max() / ref.abs().max()).item()
    assert rel <= 1e-4, rel

    classes = classes[0]  # a batch of one
    assert classes.dtype == torch.uint8 and classes.shape == hw
    ref_classes = F.interpolate(ref, size=hw, mode="bilinear", align_corners=False)[0].argmax(0)
    agree = (classes.long() == ref_classes).float().mean().item()
    assert agree >= 0.999, agree  # only near-ties may flip under 1e-7 differences of the logits
    assert len(classes.unique()) > 5  # a real map, not one class everywhere


# ------------------------------------------------------------------------------------------------- loading
@pytest.mark.parametrize("dataset", ["ade20k", "voc2012"])
@pytest.mark.parametrize("size", ["s", "b", "l", "g"])
def test_official_checkpoint_loads_strictly(tmp_path, size, dataset):
    dim, n = EMBED[size], N_CLASSES[dataset]
    sd = official_head(dim, n, seed=3)
    path = tmp_path / f"{checkpoint_name(size, dataset)}.pth"
    save_mmcv(path, sd)
    head = build_head((28, 42), (2, 3), dim, model=f"dinov2_linear_{dataset}_{size}", checkpoint=path)
    loaded = head.state_dict()
    assert set(loaded) == {k.removeprefix("decode_head.") for k in sd}
    for k, v in loaded.items():
        assert torch.equal(v, sd[f"decode_head.{k}"]), k
    assert head.default_checkpoint == f"dinov2_vit{size}14_{dataset}_linear_head"
    assert head.meta["trained_on"] == f"dinov2_vit{size}14" == SIZES[size].trained_on
    out = head(head.example_inputs())["classes"]
    assert out.dtype == torch.uint8 and out.shape == (1, 28, 42) and int(out.max()) < n


def test_checkpoint_without_batch_counter_still_loads(tmp_path):
    sd = official_head(384, 21, counter=False)
    path = tmp_path / "head.pth"
    save_mmcv(path, sd)
    head = build_head((28, 42), (2, 3), 384, model="dinov2_linear_voc2012_s", checkpoint=path)
    assert torch.equal(head.conv_seg.weight, sd["decode_head.conv_seg.weight"])


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        ("voc_into_ade", r"shape mismatches: conv_seg\.bias: checkpoint \(21,\) vs model \(150,\)"),
        ("drop_key", r"missing keys: bn\.running_var"),
        ("extra_key", r"unexpected keys: conv_seg\.extra"),
    ],
)
def test_bad_checkpoint_fails_naming_file_model_and_keys_and_loads_nothing(tmp_path, edit, message):
    sd = official_head(384, 21 if edit == "voc_into_ade" else 150, seed=5)
    if edit == "drop_key":
        del sd["decode_head.bn.running_var"]
    elif edit == "extra_key":
        sd["decode_head.conv_seg.extra"] = torch.zeros(1)
    path = tmp_path / "bad_head.pth"
    save_mmcv(path, sd)
    head = build_head((28, 42), (2, 3), 384)  # random weights
    before = {k: v.clone() for k, v in head.state_dict().items()}
    cfg = head_config((28, 42), checkpoint=path)
    specs, meta = upstream((2, 3), 384)
    ctx = BuildContext("head", "seg", cfg.heads[0], cfg, specs, meta)
    with pytest.raises(CheckpointError, match=message) as info:
        head.load_checkpoint(ctx)
    text = str(info.value)
    assert str(path) in text and "seg (dinov2_linear_ade20k_s: DINOv2 linear head, 384 channels -> 150" in text
    after = head.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before), "a failed load changed weights"


# ---------------------------------------------------------------------------------------- labels, palettes
def test_labels_and_palettes_have_the_datasets_sizes_and_known_entries():
    ade, voc = palettes.labels("ade20k"), palettes.labels("voc2012")
    assert len(ade) == 150 and len(voc) == 21
    assert ade[0] == "wall" and ade[12] == "person" and ade[20] == "car" and ade[149] == "flag"
    assert voc[0] == "background" and voc[15] == "person" and voc[7] == "car" and voc[20] == "tvmonitor"
    pa, pv = palettes.palette_bgr("ade20k"), palettes.palette_bgr("voc2012")
    assert len(pa) == 150 and len(pv) == 21
    assert pa[0] == [120, 120, 120]  # wall, grey
    assert pa[2] == [230, 230, 6]  # sky: RGB (6, 230, 230) in BGR order
    assert pv[0] == [0, 0, 0] and pv[1] == [0, 0, 128]  # aeroplane: RGB (128, 0, 0) is red, BGR puts it last
    assert pv[15] == [128, 128, 192]  # person: RGB (192, 128, 128)
    # The VOC devkit palette is the bit-interleaved colour map: rebuild it from its definition.
    for i, bgr in enumerate(pv):
        rgb, c = [0, 0, 0], i
        for j in range(8):
            for ch in range(3):
                rgb[ch] |= ((c >> ch) & 1) << (7 - j)
            c >>= 3
        assert bgr == rgb[::-1], i
    assert all(0 <= v <= 255 for col in pa + pv for v in col)
    with pytest.raises(ValueError, match=r"unknown dataset 'coco'; known: ade20k, voc2012"):
        palettes.labels("coco")


def test_head_meta_carries_labels_and_palette_usable_by_visualize():
    head = build_head((28, 42), (2, 3), 32, model="dinov2_linear_voc2012_s")
    meta = head.meta
    assert meta["kind"] == "segmentation" and meta["labels"][15] == "person"
    assert meta["palette"] == palettes.palette_bgr("voc2012") and meta["dataset"] == "voc2012"
    classes = head(head.example_inputs())["classes"][0].numpy()
    frame = np.zeros((28, 42, 3), np.uint8)
    pic = overlay_segmentation(frame, classes, np.asarray(meta["palette"], np.uint8), alpha=1.0)
    np.testing.assert_array_equal(pic, np.asarray(meta["palette"], np.uint8)[classes])


# -------------------------------------------------------------------------------- specs, planning, outputs
def test_plan_on_meta_device_with_tiny_vit_declares_specs_and_warns_about_backbone():
    cfg = load_config(
        {
            "input": {"height": 120, "width": 160},
            "weights": {"random_weights": True},  # else the other backbone is an error (test_models.py)
            "foundation_model": {"model": "tiny_vit", "options": {"embed_dim": 384, "heads": 6}},
            "heads": [
                {"name": "ade", "model": "dinov2_linear_ade20k_s"},
                {"name": "voc", "model": "dinov2_linear_voc2012_s"},
                {
                    "name": "big",
                    "model": "dinov2_linear_ade20k_s",
                    "options": {"dataset": None, "num_classes": 300},
                },
            ],
        }
    )
    plan = make_plan(cfg)
    assert {k: str(v) for k, v in plan.heads["ade"].output_spec.items()} == {"classes": "uint8[120, 160]"}
    assert str(plan.heads["big"].output_spec["classes"]) == "int16[120, 160]"
    assert set(plan.heads["voc"].input_spec) == {"patch.3"}
    assert all(p.device.type == "meta" for p in plan.heads["ade"].parameters())
    assert len(plan.heads["ade"].meta["labels"]) == 150 and len(plan.heads["voc"].meta["palette"]) == 21
    assert any("'dinov2_vits14'" in w and "'tiny_vit'" in w for w in plan.warnings)
    assert plan.heads["big"].meta["trained_on"] is None  # custom head: no released weights to warn about


def test_real_build_on_tiny_vit_gives_documented_outputs():
    cfg = load_config(
        {
            "input": {"height": 120, "width": 160},
            "foundation_model": {"model": "tiny_vit", "options": {"embed_dim": 32}},
            "heads": [{"name": "seg", "model": "dinov2_linear_ade20k_s"}],
            "weights": {"random_weights": True},
        }
    )
    plan = make_plan(cfg)
    cpu = torch.device("cpu")
    fm = build_model(cfg, "foundation", "foundation", plan.frame_spec, {}, cpu, False)
    head = build_model(cfg, "seg", "head", plan.features, plan.feature_meta, cpu, False)
    frame = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8))
    with torch.no_grad():
        feats = fm({"frame": frame[None]})
        out = head({k: feats[k] for k in head.input_spec})
    check_outputs("seg", plan.heads["seg"].output_spec, out, batch=1)
    classes = out["classes"][0]
    assert classes.dtype == torch.uint8 and classes.shape == (120, 160)
    assert int(classes.max()) < 150 and len(classes.unique()) > 1
    again = build_model(cfg, "seg", "head", plan.features, plan.feature_meta, cpu, False)
    assert torch.equal(again.conv_seg.weight, head.conv_seg.weight)  # same stand-in weights in every build


def test_more_than_256_classes_give_int16_ids():
    head = build_head((28, 42), (2, 3), 16, options={"dataset": None, "num_classes": 400})
    with torch.no_grad():
        head.conv_seg.bias.zero_()
        head.conv_seg.bias[399] = 100.0  # class 399 wins everywhere: needs more than 8 bits
        out = head(head.example_inputs())["classes"]
    assert out.dtype == torch.int16 and (out == 399).all()
    assert len(head.meta["labels"]) == len(head.meta["palette"]) == 400


def test_upsample_choice_names_why_the_fused_kernel_cannot_run():
    # The CPU: auto falls back to PyTorch, fused is refused with the reason (the kernel itself: test_upsample_argmax)
    for choice in ("auto", "torch"):
        head = build_head((28, 42), (2, 3), 32, options={"upsample": choice})
        assert head.upsample == "torch"
        out = head(head.example_inputs())["classes"]
        assert out.dtype == torch.uint8 and out.shape == (1, 28, 42)
    with pytest.raises(ModelBuildError, match=r"upsample is 'fused', which cannot run on cpu: it runs on CUDA only"):
        build_head((28, 42), (2, 3), 32, options={"upsample": "fused"})
    with pytest.raises(ModelBuildError, match=r"upsample: Input should be 'auto', 'fused' or 'torch'"):
        build_head((28, 42), (2, 3), 32, options={"upsample": "nearest"})


def test_bad_options_are_named():
    with pytest.raises(ModelBuildError, match=r"num_classes=20 contradicts dataset 'voc2012' \(21 classes\)"):
        build_head((28, 42), (2, 3), 32, model="dinov2_linear_voc2012_s", options={"num_classes": 20})
    with pytest.raises(ModelBuildError, match=r"set options.dataset \(ade20k or voc2012\) or options.num_classes"):
        build_head((28, 42), (2, 3), 32, options={"dataset": None})
    with pytest.raises(
        ModelBuildError, match=r"options\.layers: unknown key \(accepted: dataset, num_classes, size, upsample"
    ):
        build_head((28, 42), (2, 3), 32, options={"layers": 4})
    cfg = head_config((28, 42))
    specs, _ = upstream((2, 3), 32)
    with pytest.raises(ModelBuildError, match=r"patch.3 is float32\[6, 32\], expected \[4, C\]"):
        LinearSegHead.from_config(
            BuildContext("head", "seg", cfg.heads[0], cfg, specs, {"grid": (2, 2)}, defaults={"dataset": "ade20k"})
        )


def test_engine_thread_mode_delivers_class_ids_for_a_frame():
    from vpengine.engine import Engine

    cfg = {
        "mode": "thread",
        "input": {"height": 120, "width": 160},
        "foundation_model": {"model": "tiny_vit", "options": {"embed_dim": 32}, "preprocess": {"size": 112}},
        "heads": [{"name": "seg", "model": "dinov2_linear_voc2012_s"}],
        "weights": {"random_weights": True},
    }
    frame = np.random.default_rng(5).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    with Engine(cfg) as engine:
        fid = engine.submit(frame)
        result = engine.wait(fid, timeout=30)["seg"]
    classes = np.asarray(result["classes"])
    assert result.frame_id == fid
    assert classes.dtype == np.uint8 and classes.shape == (120, 160) and classes.max() < 21


def test_planning_for_cuda_chooses_the_fused_kernel_without_touching_the_gpu(monkeypatch):
    pytest.importorskip("triton")
    from vpengine.models import upsample_argmax as module

    def no_probe(index):
        raise AssertionError("planning must not run anything on the GPU")

    monkeypatch.setattr(module, "_probe", no_probe)
    cfg = heads.head_config((28, 42), {"name": "seg", "model": "dinov2_linear_ade20k_s"}, device="cuda")
    specs, meta = upstream((2, 3), 32)
    ctx = BuildContext(
        "head",
        "seg",
        cfg.heads[0],
        cfg,
        specs,
        meta,
        torch.device("meta"),
        plan_only=True,
        defaults={"dataset": "ade20k"},
    )
    assert LinearSegHead.from_config(ctx).upsample == "fused"


def test_a_gpu_triton_cannot_compile_for_is_named(monkeypatch):
    pytest.importorskip("triton")
    from vpengine.models import upsample_argmax as module

    monkeypatch.setattr(module.torch.cuda, "get_device_capability", lambda index: (6, 1))  # a Pascal GPU
    module._probe.cache_clear()
    try:
        assert module.fused_unavailable(torch.device("cuda", 1)) == (
            "Triton needs a GPU of compute capability 7.0 or newer, and cuda:1 is 6.1"
        )
        assert module.fused_unavailable(torch.device("cuda", 1), probe=False) is None  # planning asks no GPU
    finally:
        module._probe.cache_clear()
