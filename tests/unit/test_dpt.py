"""Depth-Anything-V2 DPT depth head: parity with Hugging Face's implementation, official checkpoint layout,
strict loading, specs, planning and the on-device colormap."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config

from helpers import heads
from helpers.heads import upstream
from vpengine.config import load_config
from vpengine.models.base import BuildContext, ModelBuildError, check_outputs
from vpengine.models.build import build_model
from vpengine.models.dpt import SIZES, DepthColormap, DPTDepthHead
from vpengine.models.weights import CheckpointError
from vpengine.runtime.plan import make_plan
from vpengine.visualize import colorize_depth

TINY_WIDTHS = {"features": 16, "out_channels": [8, 16, 32, 32]}


# ------------------------------------------------------------------------------------------------ helpers
def head_config(hw, options=None, checkpoint=None, model="dav2_depth_s", postprocess=None, **extra):
    head = {"name": "depth", "model": model, "options": options or {}, "postprocess": postprocess or {}}
    return heads.head_config(hw, head, checkpoint, **extra)


def build_head(hw, grid, dim, **kw):
    return heads.build_head(head_config(hw, **kw), grid, dim)


def context(cfg, grid, dim):
    specs, meta = upstream(grid, dim)
    return BuildContext("head", "depth", cfg.heads[0], cfg, specs, meta)


def official_dpt_shapes(dim, features, out_channels):
    """The ``depth_head.*`` keys and shapes of depth_anything_v2_vit*.pth, written out from the reference
    DPTHead (depth_anything_v2/dpt.py, util/blocks.py) independently of vpengine's module tree."""
    c = out_channels
    s = {}
    for i in range(4):
        s[f"depth_head.projects.{i}.weight"] = (c[i], dim, 1, 1)
        s[f"depth_head.projects.{i}.bias"] = (c[i],)
    s["depth_head.resize_layers.0.weight"] = (c[0], c[0], 4, 4)  # ConvTranspose2d: (in, out, k, k)
    s["depth_head.resize_layers.0.bias"] = (c[0],)
    s["depth_head.resize_layers.1.weight"] = (c[1], c[1], 2, 2)
    s["depth_head.resize_layers.1.bias"] = (c[1],)
    s["depth_head.resize_layers.3.weight"] = (c[3], c[3], 3, 3)
    s["depth_head.resize_layers.3.bias"] = (c[3],)
    for i in range(4):
        s[f"depth_head.scratch.layer{i + 1}_rn.weight"] = (features, c[i], 3, 3)
    for n in range(1, 5):
        p = f"depth_head.scratch.refinenet{n}"
        s[f"{p}.out_conv.weight"] = (features, features, 1, 1)
        s[f"{p}.out_conv.bias"] = (features,)
        for u in (1, 2):
            for k in (1, 2):
                s[f"{p}.resConfUnit{u}.conv{k}.weight"] = (features, features, 3, 3)
                s[f"{p}.resConfUnit{u}.conv{k}.bias"] = (features,)
    s["depth_head.scratch.output_conv1.weight"] = (features // 2, features, 3, 3)
    s["depth_head.scratch.output_conv1.bias"] = (features // 2,)
    s["depth_head.scratch.output_conv2.0.weight"] = (32, features // 2, 3, 3)
    s["depth_head.scratch.output_conv2.0.bias"] = (32,)
    s["depth_head.scratch.output_conv2.2.weight"] = (1, 32, 1, 1)
    s["depth_head.scratch.output_conv2.2.bias"] = (1,)
    return s


def random_official(dim, features, out_channels, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {
        k: torch.randn(shape, generator=g) * 0.05
        for k, shape in official_dpt_shapes(dim, features, out_channels).items()
    }


# Official (Depth-Anything-V2) -> Hugging Face (DepthAnythingForDepthEstimation) key names, as in HF's conversion.
_TO_HF = [
    (r"^projects\.(\d)\.", lambda m: f"neck.reassemble_stage.layers.{m[1]}.projection."),
    (r"^resize_layers\.(\d)\.", lambda m: f"neck.reassemble_stage.layers.{m[1]}.resize."),
    (r"^scratch\.layer(\d)_rn\.", lambda m: f"neck.convs.{int(m[1]) - 1}."),
    (
        r"^scratch\.refinenet(\d)\.resConfUnit(\d)\.conv(\d)\.",
        lambda m: f"neck.fusion_stage.layers.{4 - int(m[1])}.residual_layer{m[2]}.convolution{m[3]}.",
    ),
    (
        r"^scratch\.refinenet(\d)\.out_conv\.",
        lambda m: f"neck.fusion_stage.layers.{4 - int(m[1])}.projection.",
    ),
    (r"^scratch\.output_conv1\.", lambda m: "head.conv1."),
    (r"^scratch\.output_conv2\.0\.", lambda m: "head.conv2."),
    (r"^scratch\.output_conv2\.2\.", lambda m: "head.conv3."),
]


def official_to_hf(sd):
    out = {}
    for k, v in sd.items():
        k = k.removeprefix("depth_head.")
        for pat, repl in _TO_HF:
            new, n = re.subn(pat, repl, k)
            if n:
                out[new] = v
                break
        else:
            raise KeyError(f"no HF name for official key {k}")
    return out


def hf_model(dim, features, out_channels):
    backbone = Dinov2Config(
        hidden_size=dim,
        num_hidden_layers=4,
        num_attention_heads=2,
        intermediate_size=2 * dim,
        patch_size=14,
        image_size=518,
        out_indices=[1, 2, 3, 4],
        apply_layernorm=True,
        reshape_hidden_states=False,
    )
    cfg = DepthAnythingConfig(
        backbone_config=backbone,
        patch_size=14,
        reassemble_hidden_size=dim,
        neck_hidden_sizes=list(out_channels),
        fusion_hidden_size=features,
        head_hidden_size=32,
        depth_estimation_type="relative",
    )
    torch.manual_seed(0)
    return DepthAnythingForDepthEstimation(cfg).eval()


# ------------------------------------------------------------------------------------------- parity with HF
@pytest.mark.parametrize("hw", [(518, 518), (518, 924)], ids=lambda hw: f"{hw[0]}x{hw[1]}")
def test_depth_matches_hugging_face_depth_anything(hw):
    dim, feats, outc = 32, TINY_WIDTHS["features"], TINY_WIDTHS["out_channels"]
    grid = (hw[0] // 14, hw[1] // 14)
    hf = hf_model(dim, feats, outc)
    official = random_official(dim, feats, outc, seed=1)
    # A positive last bias keeps most pixels above the final ReLU, so the comparison is not between zeros.
    official["depth_head.scratch.output_conv2.2.bias"] = torch.tensor([0.3])
    missing, unexpected = hf.load_state_dict(official_to_hf(official), strict=False)
    assert unexpected == [] and all(k.startswith("backbone.") for k in missing)

    head = build_head(hw, grid, dim, options=TINY_WIDTHS, model="dav2_depth_s")
    head.load_state_dict({k.removeprefix("depth_head."): v for k, v in official.items()}, strict=True)

    pixels = torch.randn(1, 3, *hw, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        ref = hf(pixel_values=pixels).predicted_depth[0]
        maps = hf.backbone(pixels).feature_maps  # four layers after the final LayerNorm, CLS first
        ours = head({f"patch.{i}": maps[i][:, 1:] for i in range(4)})["depth"][0]  # a batch of one
    assert ours.dtype == torch.float32 and ours.shape == hw == tuple(ref.shape)
    assert (ref > 0).float().mean() > 0.5, "degenerate reference: mostly clipped by the final ReLU"
    rel = ((ours - ref).abs().max() / ref.abs().max()).item()
    assert rel <= 1e-4, rel


def test_official_key_layout_is_ours_and_maps_one_to_one_onto_hugging_face():
    dim, feats, outc = 32, TINY_WIDTHS["features"], TINY_WIDTHS["out_channels"]
    head = build_head((56, 56), (4, 4), dim, options=TINY_WIDTHS)
    ours = {k: tuple(v.shape) for k, v in head.state_dict().items()}
    official = {k.removeprefix("depth_head."): v for k, v in official_dpt_shapes(dim, feats, outc).items()}
    assert ours == official
    hf = hf_model(dim, feats, outc)
    hf_head = {k: tuple(v.shape) for k, v in hf.state_dict().items() if not k.startswith("backbone.")}
    converted = official_to_hf({k: torch.empty(s) for k, s in official.items()})
    assert {k: tuple(v.shape) for k, v in converted.items()} == hf_head


# ------------------------------------------------------------------------------------------------- loading
@pytest.mark.parametrize("size", ["s", "b", "l"])
def test_official_checkpoint_loads_strictly(tmp_path, size):
    dim = {"s": 384, "b": 768, "l": 1024}[size]
    sz = SIZES[size]
    sd = random_official(dim, sz.features, sz.out_channels, seed=3)
    sd["pretrained.cls_token"] = torch.zeros(1, 1, dim)  # the backbone's half of the file: ignored here
    path = tmp_path / f"depth_anything_v2_vit{size}.pth"
    torch.save(sd, path)
    head = build_head((28, 28), (2, 2), dim, model=f"dav2_depth_{size}", checkpoint=path)
    loaded = head.state_dict()
    assert len(loaded) == len(sd) - 1
    for k, v in loaded.items():
        assert torch.equal(v, sd[f"depth_head.{k}"]), k
    assert head.meta["trained_on"] == sz.trained_on and head.meta["kind"] == "depth"
    out = head(head.example_inputs())["depth"]
    assert out.shape == (1, 28, 28) and torch.isfinite(out).all() and (out >= 0).all()


def _snapshot(module):
    return {k: v.clone() for k, v in module.state_dict().items()}


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            "other_size",
            r"shape mismatches: .*projects\.0\.weight: checkpoint \(48, 384, 1, 1\) vs model \(96, 768, 1, 1\)",
        ),
        ("drop_key", r"missing keys: scratch\.output_conv2\.2\.bias"),
        ("extra_key", r"unexpected keys: scratch\.stem_transpose\.weight"),
    ],
)
def test_bad_checkpoint_fails_naming_file_model_and_keys_and_loads_nothing(tmp_path, edit, message):
    b = SIZES["b"]
    if edit == "other_size":
        s = SIZES["s"]
        sd = random_official(384, s.features, s.out_channels)
    else:
        sd = random_official(768, b.features, b.out_channels)
        if edit == "drop_key":
            del sd["depth_head.scratch.output_conv2.2.bias"]
        else:
            sd["depth_head.scratch.stem_transpose.weight"] = torch.zeros(1)
    path = tmp_path / "bad.pth"
    torch.save(sd, path)
    head = build_head((28, 28), (2, 2), 768, model="dav2_depth_b")  # random weights
    before = _snapshot(head)
    cfg = head_config((28, 28), model="dav2_depth_b", checkpoint=path)
    with pytest.raises(CheckpointError, match=message) as info:
        head.load_checkpoint(context(cfg, (2, 2), 768))
    assert str(path) in str(info.value) and "depth (dav2_depth_b" in str(info.value)
    after = head.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before), "a failed load changed weights"


def test_unreadable_checkpoint_is_a_clear_error(tmp_path):
    path = tmp_path / "truncated.pth"
    path.write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(CheckpointError, match=r"cannot read checkpoint .*truncated\.pth"):
        build_head((28, 28), (2, 2), 384, checkpoint=path)


# -------------------------------------------------------------------------------- specs, planning, outputs
def test_plan_on_meta_device_with_tiny_vit_declares_specs_and_warns_about_backbone():
    cfg = load_config(
        {
            "input": {"height": 120, "width": 160},
            "weights": {"random_weights": True},  # else the other backbone is an error (test_models.py)
            "foundation_model": {"model": "tiny_vit", "options": {"embed_dim": 384, "heads": 6}},
            "heads": [
                {"name": "raw", "model": "dav2_depth_s"},
                {"name": "both", "model": "dav2_depth_l", "postprocess": {"output": "both"}},
                {"name": "pic", "model": "dav2_depth_b", "postprocess": {"output": "colormap"}},
            ],
        }
    )
    plan = make_plan(cfg)
    assert plan.heads["raw"].output_spec == {"depth": plan.heads["raw"].output_spec["depth"]}
    assert str(plan.heads["raw"].output_spec["depth"]) == "float32[120, 160]"
    both = {k: str(v) for k, v in plan.heads["both"].output_spec.items()}
    assert both == {"depth": "float32[120, 160]", "depth_color": "uint8[120, 160, 3]"}
    assert {k: str(v) for k, v in plan.heads["pic"].output_spec.items()} == {"depth_color": "uint8[120, 160, 3]"}
    assert set(plan.heads["raw"].input_spec) == {f"patch.{i}" for i in range(4)}
    assert all(p.device.type == "meta" for p in plan.heads["both"].parameters())
    assert any("'dinov2_vits14_dav2'" in w and "'tiny_vit'" in w for w in plan.warnings)
    assert plan.heads["both"].meta["kind"] == "depth"


def test_real_build_on_tiny_vit_gives_documented_outputs():
    cfg = load_config(
        {
            "input": {"height": 120, "width": 160},
            "foundation_model": {"model": "tiny_vit", "options": {"embed_dim": 32}},
            "heads": [
                {
                    "name": "depth",
                    "model": "dav2_depth_s",
                    "options": TINY_WIDTHS,
                    "postprocess": {"output": "both"},
                }
            ],
            "weights": {"random_weights": True},
        }
    )
    plan = make_plan(cfg)
    cpu = torch.device("cpu")
    fm = build_model(cfg, "foundation", "foundation", plan.frame_spec, {}, cpu, False)
    head = build_model(cfg, "depth", "head", plan.features, plan.feature_meta, cpu, False)
    frame = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8))
    with torch.no_grad():
        feats = fm({"frame": frame[None]})
        out = head({k: feats[k] for k in head.input_spec})
    check_outputs("depth", plan.heads["depth"].output_spec, out, batch=1)
    depth, color = out["depth"][0], out["depth_color"][0]
    assert depth.dtype == torch.float32 and torch.isfinite(depth).all() and (depth >= 0).all()
    assert depth.std() > 0
    np.testing.assert_array_equal(color.numpy(), colorize_depth(depth.numpy()))


def test_random_weights_are_the_same_in_every_build():
    # Process-mode workers and restarted workers build their own copy: it must be the same model.
    a = build_head((56, 84), (4, 6), 32, options=TINY_WIDTHS)
    torch.manual_seed(123)  # the global RNG must not matter
    b = build_head((56, 84), (4, 6), 32, options=TINY_WIDTHS)
    sa, sb = a.state_dict(), b.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)


def test_reduced_precision_still_outputs_float32_depth_close_to_fp32():
    hw, grid, dim = (56, 84), (4, 6), 32
    ref_head = build_head(hw, grid, dim, options=TINY_WIDTHS)
    bf16 = build_head(hw, grid, dim, options=TINY_WIDTHS, precision="bf16")
    bf16.load_state_dict(ref_head.state_dict())
    assert bf16.scratch.layer1_rn.weight.dtype == torch.bfloat16
    inputs = ref_head.example_inputs()
    with torch.no_grad():
        ref, low = ref_head(inputs)["depth"], bf16(inputs)["depth"]
    assert low.dtype == torch.float32 and low.shape == (1, *hw)
    assert ((low - ref).abs().max() / ref.abs().max()).item() < 0.1


def test_final_resize_to_input_resolution_uses_align_corners_like_reference():
    # A frame of 100x150 seen by the backbone as 56x84 (4x6 tokens): the head must resize 56x84 -> 100x150.
    head = build_head((100, 150), (4, 6), 32, options=TINY_WIDTHS)
    inputs = head.example_inputs()
    head.out_hw = (56, 84)  # the same weights, evaluated at backbone resolution
    with torch.no_grad():
        at_backbone = head(inputs)["depth"]
        head.out_hw = (100, 150)
        full = head(inputs)["depth"]
    expected = torch.nn.functional.interpolate(at_backbone[:, None], (100, 150), mode="bilinear", align_corners=True)[
        :, 0
    ]
    torch.testing.assert_close(full, expected)
    # align_corners=True keeps the corner pixels exactly
    assert full[0, 0, 0] == at_backbone[0, 0, 0] and full[0, -1, -1] == at_backbone[0, -1, -1]


# ---------------------------------------------------------------------------------------------- colormap
def test_device_colormap_equals_visualize_colorize_depth():
    rng = np.random.default_rng(0)
    depth = (rng.random((37, 53), dtype=np.float32) * 40 + 3).astype(np.float32)
    depth[3, 4], depth[10, 11], depth[0, 0] = np.nan, np.inf, -np.inf
    cm = DepthColormap((37, 53), keep_depth=True)
    out = cm({"depth": torch.from_numpy(depth)[None]})
    np.testing.assert_array_equal(out["depth_color"][0].numpy(), colorize_depth(depth))
    assert out["depth"] is not None and (out["depth_color"][0, 3, 4] == 0).all()
    flat = DepthColormap((4, 5))({"depth": torch.full((1, 4, 5), 2.0)})  # hi == lo: no division by zero
    assert set(flat) == {"depth_color"}
    np.testing.assert_array_equal(flat["depth_color"][0].numpy(), colorize_depth(np.full((4, 5), 2.0, np.float32)))


def test_device_colormap_scales_each_frame_of_a_batch_by_its_own_range():
    rng = np.random.default_rng(1)
    near = (rng.random((6, 7), dtype=np.float32) * 2 + 1).astype(np.float32)  # 1..3
    far = (rng.random((6, 7), dtype=np.float32) * 90 + 10).astype(np.float32)  # 10..100
    far[2, 3] = np.nan
    out = DepthColormap((6, 7))({"depth": torch.from_numpy(np.stack([near, far, near]))})["depth_color"]
    for i, d in enumerate((near, far, near)):  # as if each frame were alone: never scaled by the other's range
        np.testing.assert_array_equal(out[i].numpy(), colorize_depth(d))


# ----------------------------------------------------------------------------------------- config errors
def test_bad_options_and_postprocess_are_named():
    with pytest.raises(ModelBuildError, match=r"set options.size \(one of s, b, l\) or both options.features"):
        build_head((28, 28), (2, 2), 32, options={"size": None})
    with pytest.raises(
        ModelBuildError,
        match=r"bad options for .*: heads\.\w+\.options\.size: Input should be 's', 'b' or 'l' \(got 'x'\)",
    ):
        build_head((28, 28), (2, 2), 32, options={"size": "x"})
    with pytest.raises(
        ModelBuildError,
        match=r"bad postprocess options for .*: heads\.\w+\.postprocess\.output: .*accepted: cmap, output",
    ):
        build_head((28, 28), (2, 2), 32, postprocess={"output": "jet"})
    with pytest.raises(ModelBuildError, match=r"cmap: .*unknown colormap 'nope'; accepted: Spectral_r"):
        build_head((28, 28), (2, 2), 32, postprocess={"output": "both", "cmap": "nope"})


def test_missing_grid_or_mismatched_tokens_fail_at_build():
    cfg = head_config((28, 28))
    specs, _ = upstream((2, 2), 32)
    size_s = {"size": "s"}
    with pytest.raises(ModelBuildError, match=r"needs the foundation model's token grid"):
        DPTDepthHead.from_config(BuildContext("head", "depth", cfg.heads[0], cfg, specs, {}, defaults=size_s))
    with pytest.raises(ModelBuildError, match=r"patch.0 is float32\[4, 32\], expected \[6, C\]"):
        DPTDepthHead.from_config(
            BuildContext("head", "depth", cfg.heads[0], cfg, specs, {"grid": (2, 3)}, defaults=size_s)
        )


def test_custom_widths_have_no_default_checkpoint_or_trained_on():
    head = build_head((28, 28), (2, 2), 32, options=TINY_WIDTHS)
    assert head.default_checkpoint is None and head.meta["trained_on"] is None
    s = build_head((28, 28), (2, 2), 384)
    assert s.default_checkpoint == "depth_anything_v2_vits"


def test_engine_thread_mode_delivers_depth_and_colormap_for_a_frame():
    from vpengine.engine import Engine

    cfg = {
        "mode": "thread",
        "input": {"height": 120, "width": 160},
        "foundation_model": {"model": "tiny_vit", "options": {"embed_dim": 32}, "preprocess": {"size": 112}},
        "heads": [
            {
                "name": "depth",
                "model": "dav2_depth_s",
                "options": TINY_WIDTHS,
                "postprocess": {"output": "both"},
            }
        ],
        "weights": {"random_weights": True},
    }
    frame = np.random.default_rng(5).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    with Engine(cfg) as engine:
        fid = engine.submit(frame)
        result = engine.wait(fid, timeout=30)["depth"]
    depth, color = np.asarray(result["depth"]), np.asarray(result["depth_color"])
    assert result.frame_id == fid
    assert depth.dtype == np.float32 and depth.shape == (120, 160) and (depth >= 0).all() and depth.std() > 0
    assert color.dtype == np.uint8 and color.shape == (120, 160, 3)
    np.testing.assert_array_equal(color, colorize_depth(depth))


def test_cls_token_readout_and_batchnorm_variants_follow_the_reference_layout():
    dim, opts = 32, {**TINY_WIDTHS, "use_clstoken": True, "use_bn": True}
    head = build_head((56, 56), (4, 4), dim, options=opts)
    assert set(head.input_spec) == {f"{k}.{i}" for k in ("patch", "cls") for i in range(4)}
    shapes = {k: tuple(v.shape) for k, v in head.state_dict().items()}
    for i in range(4):  # readout_projects.i = Sequential(Linear(2C, C), GELU)
        assert shapes[f"readout_projects.{i}.0.weight"] == (dim, 2 * dim)
    assert shapes["scratch.refinenet2.resConfUnit1.bn2.running_var"] == (TINY_WIDTHS["features"],)
    plain = {k.removeprefix("depth_head."): s for k, s in official_dpt_shapes(dim, 16, [8, 16, 32, 32]).items()}
    extra = set(shapes) - set(plain)
    assert extra and all(k.startswith("readout_projects.") or ".bn" in k for k in extra)
    inputs = head.example_inputs()
    with torch.no_grad():
        a = head(inputs)["depth"]
        inputs["cls.2"] = inputs["cls.2"] + 1.0
        b = head(inputs)["depth"]
    assert not torch.equal(a, b), "the CLS token must reach the output when use_clstoken is set"
