"""DINOv2 foundation model: parity with Hugging Face transformers, checkpoint layouts, bad files, planning.

Reference facts used here and written independently of ``vpengine.models.dinov2``: the official DINOv2 key names
and shapes (facebookresearch/dinov2 ``DinoVisionTransformer``), the Hugging Face hub key names (what
``save_pretrained`` writes), and the released sizes (S 384/12/6, B 768/12/12, L 1024/24/16, G 1536/40/24 with a
4096-wide SwiGLU).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import torch
import torch.nn.functional as F
import transformers

from vpengine.config import load_config
from vpengine.models.base import BuildContext, ModelBuildError, check_outputs
from vpengine.models.dinov2 import DinoV2
from vpengine.models.registry import resolve
from vpengine.models.weights import CheckpointError, read_state_dict
from vpengine.runtime.plan import make_plan
from vpengine.specs import TensorSpec

TINY = {"size": "custom", "embed_dim": 32, "depth": 4, "heads": 2}
# (embed, depth, heads, swiglu hidden or None)
RELEASED = {
    "s": (384, 12, 6, None),
    "b": (768, 12, 12, None),
    "l": (1024, 24, 16, None),
    "g": (1536, 40, 24, 4096),
}
META_WARNING = "ignore:for .*copying from a non-meta parameter"


# ------------------------------------------------------------------------------------------------- helpers
def engine_cfg(model: str, hw: tuple[int, int], options: dict | None = None, checkpoint: str | None = None, **kw):
    """An engine config whose preprocessing keeps ``hw`` as is (so the backbone sees exactly ``hw``)."""
    raw: dict[str, Any] = {
        "input": {"height": hw[0], "width": hw[1]},
        "foundation_model": {
            "model": model,
            "options": options or {},
            "checkpoint": checkpoint,
            "preprocess": {"resize": "none"},
        },
    }
    for k, v in kw.items():
        raw[k] = v
    return load_config(raw)


def build_ctx(cfg) -> BuildContext:
    _, defaults = resolve(cfg.foundation_model.model, "foundation")
    frame = {"frame": TensorSpec((cfg.input.height, cfg.input.width, 3), "uint8")}
    return BuildContext(
        "foundation", "foundation", cfg.foundation_model, cfg, frame, {}, torch.device("cpu"), False, defaults
    )


def build_backbone(cfg, device: str = "cpu") -> tuple[DinoV2, BuildContext]:
    ctx = build_ctx(cfg)
    with torch.device(device):
        pipe = DinoV2.from_config(ctx)
    model = pipe.stages[1]
    assert isinstance(model, DinoV2)
    return model.eval(), ctx


def tiny_model(hw=(518, 518), **options) -> DinoV2:
    model, _ = build_backbone(engine_cfg("dinov2_vits14", hw, {**TINY, **options}))
    return model


def randomize_(module: torch.nn.Module, seed: int) -> None:
    """Every parameter random and O(1)-scaled, so that each one (layer scale, biases, norms, position embeddings)
    shows up in the output: the initial values of timm and HF (layer scale 1e-5, zero biases) would hide bugs."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in module.named_parameters():
            r = torch.randn(p.shape, generator=g)
            if re.search(r"(norm\d?|layernorm)\.weight$", name):
                p.copy_(1 + 0.1 * r)
            elif p.ndim >= 2 and "token" not in name and "pos" not in name and "position" not in name:
                p.copy_(r / p[0].numel() ** 0.5)  # weights: unit gain
            elif "gamma" in name or "lambda1" in name:
                p.copy_(0.3 + 0.1 * r)
            elif "mask_token" in name:
                p.zero_()
            else:  # biases, class/register tokens, position embeddings
                p.copy_(0.5 * r)


def image(hw: tuple[int, int], seed: int = 0) -> torch.Tensor:
    return torch.randn(1, 3, *hw, generator=torch.Generator().manual_seed(seed))


def hf_config(embed: int, depth: int, heads: int, registers: int, swiglu: bool):
    kw = dict(
        hidden_size=embed,
        num_hidden_layers=depth,
        num_attention_heads=heads,
        mlp_ratio=4,
        image_size=518,
        patch_size=14,
        use_swiglu_ffn=swiglu,
        layer_norm_eps=1e-6,
    )
    if registers:
        return transformers.Dinov2WithRegistersConfig(num_register_tokens=registers, **kw)
    return transformers.Dinov2Config(**kw)


def hf_model(cfg):
    cls = transformers.Dinov2WithRegistersModel if hasattr(cfg, "num_register_tokens") else transformers.Dinov2Model
    return cls(cfg).eval()


def hf_features(hf, img: torch.Tensor, layers: list[int], registers: int) -> dict[str, torch.Tensor]:
    """DINOv2's get_intermediate_layers(n=layers, norm=True, return_class_token=True), computed by HF."""
    with torch.no_grad():
        hidden = hf(pixel_values=img, output_hidden_states=True).hidden_states  # embeddings, then every block
        out = {}
        for k, layer in enumerate(layers):
            y = hf.layernorm(hidden[layer + 1])
            out[f"patch.{k}"] = y[:, 1 + registers :]
            out[f"cls.{k}"] = y[:, 0]
    return out


def ours_to_hf(sd: dict[str, torch.Tensor], registers: int, swiglu: bool) -> dict[str, torch.Tensor]:
    """Our (timm) state dict in the module names of transformers >= 5 (q_proj, gate_proj, ...)."""
    out: dict[str, torch.Tensor] = {}
    cls, pos = sd["cls_token"], sd["pos_embed"]
    c = cls.shape[-1]
    if registers:  # timm folds the class position into the class token; HF adds it: give HF a zero one
        pos = torch.cat([torch.zeros(1, 1, c), pos], 1)
        out["embeddings.register_tokens"] = sd["reg_token"]
    out["embeddings.cls_token"] = cls
    out["embeddings.position_embeddings"] = pos
    out["embeddings.mask_token"] = torch.zeros(1, c)
    out["embeddings.patch_embeddings.projection.weight"] = sd["patch_embed.proj.weight"]
    out["embeddings.patch_embeddings.projection.bias"] = sd["patch_embed.proj.bias"]
    out["layernorm.weight"], out["layernorm.bias"] = sd["norm.weight"], sd["norm.bias"]
    depth = 1 + max(int(k.split(".")[1]) for k in sd if k.startswith("blocks."))
    for i in range(depth):
        b, h = f"blocks.{i}.", f"encoder.layer.{i}."
        for p in ("weight", "bias"):
            q, k, v = sd[f"{b}attn.qkv.{p}"].chunk(3, 0)
            (
                out[f"{h}attention.q_proj.{p}"],
                out[f"{h}attention.k_proj.{p}"],
                out[f"{h}attention.v_proj.{p}"],
            ) = q, k, v
            out[f"{h}attention.o_proj.{p}"] = sd[f"{b}attn.proj.{p}"]
            out[f"{h}norm1.{p}"], out[f"{h}norm2.{p}"] = sd[f"{b}norm1.{p}"], sd[f"{b}norm2.{p}"]
            if swiglu:
                gate, up = sd[f"{b}mlp.fc1.{p}"].chunk(2, 0)
                out[f"{h}mlp.gate_proj.{p}"], out[f"{h}mlp.up_proj.{p}"] = gate, up
                out[f"{h}mlp.down_proj.{p}"] = sd[f"{b}mlp.fc2.{p}"]
            else:
                out[f"{h}mlp.fc1.{p}"], out[f"{h}mlp.fc2.{p}"] = sd[f"{b}mlp.fc1.{p}"], sd[f"{b}mlp.fc2.{p}"]
        out[f"{h}layer_scale1.lambda1"] = sd[f"{b}ls1.gamma"]
        out[f"{h}layer_scale2.lambda1"] = sd[f"{b}ls2.gamma"]
    return out


def assert_features_close(ours: dict[str, torch.Tensor], ref: dict[str, torch.Tensor], tol: float = 1e-4) -> None:
    assert set(ours) == set(ref) == {f"{k}.{i}" for k in ("patch", "cls") for i in range(4)}
    for k in ref:
        assert ours[k].shape == ref[k].shape, k
        rel = ((ours[k] - ref[k]).abs().max() / ref[k].abs().max()).item()
        assert rel <= tol, f"{k}: relative error {rel:.2e} > {tol:.0e}"


def official_shapes(
    embed: int, depth: int, heads: int, swiglu_hidden: int | None, registers: int
) -> dict[str, tuple[int, ...]]:
    """Names and shapes of facebookresearch/dinov2's *_pretrain.pth (518-pixel pretraining: 37 x 37 positions)."""
    c = embed
    shapes: dict[str, tuple[int, ...]] = {
        "cls_token": (1, 1, c),
        "pos_embed": (1, 1 + 37 * 37, c),
        "mask_token": (1, c),
        "patch_embed.proj.weight": (c, 3, 14, 14),
        "patch_embed.proj.bias": (c,),
        "norm.weight": (c,),
        "norm.bias": (c,),
    }
    if registers:
        shapes["register_tokens"] = (1, registers, c)
    for i in range(depth):
        b = f"blocks.{i}."
        shapes |= {
            b + "norm1.weight": (c,),
            b + "norm1.bias": (c,),
            b + "attn.qkv.weight": (3 * c, c),
            b + "attn.qkv.bias": (3 * c,),
            b + "attn.proj.weight": (c, c),
            b + "attn.proj.bias": (c,),
            b + "ls1.gamma": (c,),
            b + "norm2.weight": (c,),
            b + "norm2.bias": (c,),
            b + "ls2.gamma": (c,),
        }
        if swiglu_hidden:
            hid = swiglu_hidden
            shapes |= {
                b + "mlp.w12.weight": (2 * hid, c),
                b + "mlp.w12.bias": (2 * hid,),
                b + "mlp.w3.weight": (c, hid),
                b + "mlp.w3.bias": (c,),
            }
        else:
            shapes |= {
                b + "mlp.fc1.weight": (4 * c, c),
                b + "mlp.fc1.bias": (4 * c,),
                b + "mlp.fc2.weight": (c, 4 * c),
                b + "mlp.fc2.bias": (c,),
            }
    return shapes


def hf_hub_shapes(official: dict[str, tuple[int, ...]]) -> dict[str, tuple[int, ...]]:
    """The same tensors under the Hugging Face hub names (facebook/dinov2-*, dinov2-with-registers-*)."""
    out: dict[str, tuple[int, ...]] = {}
    for k, s in official.items():
        m = re.match(r"blocks\.(\d+)\.(.*)", k)
        if not m:
            name = {
                "cls_token": "embeddings.cls_token",
                "pos_embed": "embeddings.position_embeddings",
                "mask_token": "embeddings.mask_token",
                "register_tokens": "embeddings.register_tokens",
                "patch_embed.proj.weight": "embeddings.patch_embeddings.projection.weight",
                "patch_embed.proj.bias": "embeddings.patch_embeddings.projection.bias",
                "norm.weight": "layernorm.weight",
                "norm.bias": "layernorm.bias",
            }[k]
            out[name] = s
            continue
        h, rest = f"encoder.layer.{m.group(1)}.", m.group(2)
        if rest.startswith("attn.qkv."):
            p = rest.rsplit(".", 1)[1]
            for q in ("query", "key", "value"):
                out[f"{h}attention.attention.{q}.{p}"] = (s[0] // 3, *s[1:])
            continue
        rest = (
            rest.replace("attn.proj", "attention.output.dense")
            .replace("ls1.gamma", "layer_scale1.lambda1")
            .replace("ls2.gamma", "layer_scale2.lambda1")
            .replace("mlp.w12", "mlp.weights_in")
            .replace("mlp.w3", "mlp.weights_out")
        )
        out[h + rest] = s
    return out


def strided_zeros(shapes: dict[str, tuple[int, ...]]) -> dict[str, torch.Tensor]:
    """Full-shaped tensors backed by one element each: a ViT-G checkpoint on disk in a few kilobytes."""
    return {k: torch.zeros(()).expand(s) for k, s in shapes.items()}


def random_tensors(shapes: dict[str, tuple[int, ...]], seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {k: torch.randn(s, generator=g) * 0.1 for k, s in shapes.items()}


def snapshot(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in model.state_dict().items()}


def assert_unchanged(model: torch.nn.Module, before: dict[str, torch.Tensor]) -> None:
    after = model.state_dict()
    assert after.keys() == before.keys()
    assert all(torch.equal(after[k], before[k]) for k in before)


# ------------------------------------------------------------------------------ parity with Hugging Face
VARIANTS = [
    pytest.param(0, False, id="plain"),
    pytest.param(4, False, id="reg4"),
    pytest.param(0, True, id="swiglu"),
    pytest.param(4, True, id="swiglu-reg4"),
]


@pytest.mark.parametrize(("registers", "swiglu"), VARIANTS)
@pytest.mark.parametrize("hw", [(518, 518), (518, 924)], ids=["518x518", "518x924"])
def test_hf_weights_load_from_a_saved_safetensors_file_and_match_hf_outputs(tmp_path, registers, swiglu, hw):
    """HF -> ours: a real HF model saved with save_pretrained (hub key layout) loads through load_checkpoint."""
    hf = hf_model(hf_config(32, 4, 2, registers, swiglu))
    randomize_(hf, seed=1)
    hf.save_pretrained(tmp_path)
    path = tmp_path / "model.safetensors"
    assert "embeddings.cls_token" in read_state_dict(path)  # really the hub layout
    options = {**TINY, "registers": registers, "swiglu": swiglu}
    model, ctx = build_backbone(engine_cfg("dinov2_vits14", hw, options, checkpoint=str(path)))
    model.load_checkpoint(ctx)
    img = image(hw)
    with torch.no_grad():
        ours = model({"image": img})
    assert_features_close(ours, hf_features(hf, img, model.layers, registers))


@pytest.mark.parametrize(("registers", "swiglu"), VARIANTS)
@pytest.mark.parametrize("hw", [(518, 518), (518, 924)], ids=["518x518", "518x924"])
def test_our_weights_converted_into_hf_give_the_same_features(registers, swiglu, hw):
    """Ours -> HF: our random weights, renamed in this test into HF's modules (strict load), same features."""
    model = tiny_model(hw, registers=registers, swiglu=swiglu, layers=[0, 1, 3, 5], depth=6)
    randomize_(model.vit, seed=2)
    model.refresh_position_cache()
    hf = hf_model(hf_config(32, 6, 2, registers, swiglu))
    hf.load_state_dict(ours_to_hf(model.vit.state_dict(), registers, swiglu), strict=True)
    img = image(hw, seed=3)
    with torch.no_grad():
        ours = model({"image": img})
    assert_features_close(ours, hf_features(hf, img, [0, 1, 3, 5], registers))


def test_the_other_interpolation_differs_so_parity_tests_can_fail(tmp_path):
    """At 518x924 the original-repo interpolation (+0.1 offset) is measurably different from HF's: a wrong
    interpolation cannot pass the 1e-4 parity checks above."""
    hf = hf_model(hf_config(32, 4, 2, 0, False))
    randomize_(hf, seed=1)
    hf.save_pretrained(tmp_path)
    opts = {**TINY, "pos_embed_interpolation": "dinov2"}
    model, ctx = build_backbone(engine_cfg("dinov2_vits14", (518, 924), opts, str(tmp_path / "model.safetensors")))
    model.load_checkpoint(ctx)
    img = image((518, 924))
    with torch.no_grad():
        ours = model({"image": img})
    ref = hf_features(hf, img, model.layers, 0)
    rel = ((ours["patch.0"] - ref["patch.0"]).abs().max() / ref["patch.0"].abs().max()).item()
    assert rel > 1e-3


@pytest.mark.parametrize("registers", [0, 4])
def test_dinov2_interpolation_option_reproduces_the_original_repositories(registers):
    """facebookresearch/dinov2 and Depth-Anything-V2: scale_factor (g + 0.1) / 37 without antialias for models
    without registers; exact size with antialias for register models."""
    model = tiny_model((518, 924), registers=registers, pos_embed_interpolation="dinov2")
    pos = model.vit.pos_embed.detach()
    grid = pos if registers else pos[:, 1:]
    x = grid.reshape(1, 37, 37, 32).permute(0, 3, 1, 2)
    if registers:
        ref = F.interpolate(x, size=(37, 66), mode="bicubic", antialias=True)
    else:
        ref = F.interpolate(x, scale_factor=(37.1 / 37, 66.1 / 37), mode="bicubic", antialias=False)
    ref = ref.permute(0, 2, 3, 1).reshape(1, 37 * 66, 32)
    torch.testing.assert_close(model.patch_pos, ref)


def test_released_vit_s_configuration_matches_hf_at_518():
    hf = hf_model(hf_config(384, 12, 6, 0, False))
    randomize_(hf, seed=4)
    model, _ = build_backbone(engine_cfg("dinov2_vits14", (518, 518)))
    sd = {k: v for k, v in hf.state_dict().items()}
    # HF -> ours through the converter used for checkpoints, from transformers-5 in-memory names this time
    assert "encoder.layer.0.attention.q_proj.weight" in sd
    assert model.load_state_dict_any(sd, "in-memory HF ViT-S") == "hf"
    img = image((518, 518), seed=5)
    with torch.no_grad():
        ours = model({"image": img})
    assert model.layers == [2, 5, 8, 11]
    assert_features_close(ours, hf_features(hf, img, [2, 5, 8, 11], 0))


def test_load_state_dict_refreshes_the_precomputed_position_embedding():
    a = tiny_model((518, 924), seed=1)
    b = tiny_model((518, 924), seed=2)
    randomize_(b.vit, seed=3)
    b.refresh_position_cache()
    img = image((518, 924))
    assert not torch.equal(a.patch_pos, b.patch_pos)
    a.load_state_dict(b.state_dict())
    with torch.no_grad():
        ya, yb = a({"image": img}), b({"image": img})
    for k in yb:
        torch.testing.assert_close(ya[k], yb[k], rtol=0, atol=0)


# ------------------------------------------------------------------------------------ checkpoint layouts
SIZES_REG = [pytest.param(s, r, id=f"{s}{'-reg4' if r else ''}") for s in RELEASED for r in (0, 4)]


def recipe(size: str, registers: int) -> str:
    return f"dinov2_vit{size}14" + ("_reg4" if registers else "")


@pytest.mark.filterwarnings(META_WARNING)
@pytest.mark.parametrize(("size", "registers"), SIZES_REG)
def test_official_pth_files_load_strictly_for_every_release(tmp_path, size, registers):
    """Exactly the official names and shapes, from a real .pth file, through load_checkpoint (meta model)."""
    path = tmp_path / f"dinov2_vit{size}14_pretrain.pth"
    torch.save(strided_zeros(official_shapes(*RELEASED[size], registers)), path)
    model, ctx = build_backbone(engine_cfg(recipe(size, registers), (518, 924), checkpoint=str(path)), "meta")
    model.load_checkpoint(ctx)  # raises if a single name or shape differs
    assert model.patch_pos.shape == (1, 37 * 66, RELEASED[size][0])


@pytest.mark.filterwarnings(META_WARNING)
@pytest.mark.parametrize(("size", "registers"), SIZES_REG)
def test_hf_hub_layout_loads_strictly_for_every_release(size, registers):
    sd = {
        k: torch.empty(s, device="meta") for k, s in hf_hub_shapes(official_shapes(*RELEASED[size], registers)).items()
    }
    model, _ = build_backbone(engine_cfg(recipe(size, registers), (518, 924)), "meta")
    assert model.load_state_dict_any(sd, "hub-layout") == "hf"


@pytest.mark.filterwarnings(META_WARNING)
@pytest.mark.parametrize("size", ["s", "b", "l"])
def test_depth_anything_v2_files_load_the_pretrained_encoder_and_ignore_the_head(tmp_path, size):
    sd = {f"pretrained.{k}": v for k, v in strided_zeros(official_shapes(*RELEASED[size], 0)).items()}
    sd["depth_head.projects.0.weight"] = torch.zeros(()).expand(48, RELEASED[size][0], 1, 1)
    sd["depth_head.scratch.output_conv2.2.bias"] = torch.zeros(1)
    path = tmp_path / f"depth_anything_v2_vit{size}.pth"
    torch.save(sd, path)
    model, ctx = build_backbone(engine_cfg(f"dinov2_vit{size}14_dav2", (518, 924), checkpoint=str(path)), "meta")
    model.load_checkpoint(ctx)
    assert model.meta["backbone"] == f"dinov2_vit{size}14_dav2"
    assert model.default_checkpoint == f"depth_anything_v2_vit{size}"


@pytest.mark.parametrize(
    ("registers", "swiglu", "prefix"),
    [(0, False, ""), (4, False, ""), (0, True, ""), (0, False, "pretrained.")],
    ids=["official", "official-reg4", "official-swiglu", "dav2"],
)
def test_official_values_land_where_they_belong(tmp_path, registers, swiglu, prefix):
    """Real values: the class token absorbs its position embedding for register models (as timm does), SwiGLU
    w12/w3 become the packed fc1/fc2, everything else is copied as is."""
    official = random_tensors(official_shapes(32, 4, 2, 88 if swiglu else None, registers))
    path = tmp_path / "ckpt.pth"
    torch.save({prefix + k: v for k, v in official.items()}, path)
    opts = {**TINY, "registers": registers, "swiglu": swiglu}
    model, ctx = build_backbone(engine_cfg("dinov2_vits14", (518, 924), opts, checkpoint=str(path)))
    model.load_checkpoint(ctx)
    vit = model.vit
    torch.testing.assert_close(vit.blocks[2].attn.qkv.weight, official["blocks.2.attn.qkv.weight"], rtol=0, atol=0)
    torch.testing.assert_close(vit.blocks[1].ls2.gamma, official["blocks.1.ls2.gamma"], rtol=0, atol=0)
    if swiglu:
        torch.testing.assert_close(vit.blocks[3].mlp.fc1.weight, official["blocks.3.mlp.w12.weight"], rtol=0, atol=0)
        torch.testing.assert_close(vit.blocks[3].mlp.fc2.bias, official["blocks.3.mlp.w3.bias"], rtol=0, atol=0)
    if registers:
        cls = official["cls_token"] + official["pos_embed"][:, :1]
        torch.testing.assert_close(vit.cls_token, cls)
        torch.testing.assert_close(vit.reg_token, official["register_tokens"], rtol=0, atol=0)
        torch.testing.assert_close(vit.pos_embed, official["pos_embed"][:, 1:], rtol=0, atol=0)
    else:
        torch.testing.assert_close(vit.pos_embed, official["pos_embed"], rtol=0, atol=0)


# ------------------------------------------------------------------------------------- bad checkpoints
@pytest.fixture(scope="module")
def vit_s():
    """A real ViT-S (random weights) for the bad-checkpoint tests; each test checks it is left unchanged."""
    model, _ = build_backbone(engine_cfg("dinov2_vits14", (224, 224)))
    return model


def _load_file(model: DinoV2, path: Path) -> None:
    cfg = engine_cfg("dinov2_vits14", (224, 224), checkpoint=str(path))
    model.load_checkpoint(build_ctx(cfg))


def _bad(tmp_path: Path, kind: str) -> tuple[Path, list[str]]:
    """A bad checkpoint and the fragments its error must contain (besides file and model)."""
    s = official_shapes(*RELEASED["s"], 0)
    if kind == "dpt-only":
        sd = {
            "depth_head.projects.0.weight": torch.zeros(48, 384, 1, 1),
            "depth_head.scratch.layer1_rn.weight": torch.zeros(64, 48, 3, 3),
        }
        frags = [
            "no DINOv2 key layout was recognised",
            "depth_head.projects.0.weight",
            "missing keys: blocks.0.",
        ]
    elif kind == "unrelated":
        sd = {"conv1.weight": torch.zeros(64, 3, 7, 7), "fc.weight": torch.zeros(1000, 2048)}
        frags = [
            "no DINOv2 key layout was recognised",
            "conv1.weight",
            "unexpected keys: conv1.weight, fc.weight",
        ]
    elif kind == "vit-b":
        sd = strided_zeros(official_shapes(*RELEASED["b"], 0))
        frags = [
            "shape mismatches",
            "checkpoint (2304, 768) vs model (1152, 384)",
            "file layout: official; it holds a DINOv2 with embed 768, 12 blocks, 0 registers",
        ]
    elif kind == "reg4-into-plain":
        sd = strided_zeros(official_shapes(*RELEASED["s"], 4))
        frags = [
            "unexpected keys: reg_token",
            "pos_embed: checkpoint (1, 1369, 384) vs model (1, 1370, 384)",
            "embed 384, 12 blocks, 4 registers",
        ]
    elif kind == "missing-blocks":
        sd = strided_zeros({k: v for k, v in s.items() if not k.startswith("blocks.11.")})
        frags = ["missing keys: blocks.11.attn.proj.bias"]
    elif kind in ("truncated-pth", "truncated-safetensors"):
        full = random_tensors({k: v for k, v in s.items() if not k.startswith("blocks.1")})
        if kind == "truncated-pth":
            path = tmp_path / "truncated.pth"
            torch.save(full, path)
        else:
            from safetensors.torch import save_file

            path = tmp_path / "truncated.safetensors"
            save_file(full, str(path))
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
        return path, ["cannot read checkpoint"]
    else:  # pragma: no cover
        raise AssertionError(kind)
    path = tmp_path / f"{kind}.pth"
    torch.save(sd, path)
    return path, frags


@pytest.mark.parametrize(
    "kind",
    [
        "dpt-only",
        "unrelated",
        "vit-b",
        "reg4-into-plain",
        "missing-blocks",
        "truncated-pth",
        "truncated-safetensors",
    ],
)
def test_bad_checkpoints_fail_naming_file_model_and_keys_and_change_nothing(tmp_path, vit_s, kind):
    path, fragments = _bad(tmp_path, kind)
    before = snapshot(vit_s)
    pos_before = vit_s.patch_pos.clone()
    with pytest.raises(CheckpointError) as e:
        _load_file(vit_s, path)
    msg = str(e.value)
    assert str(path) in msg
    assert "foundation (dinov2_vits14: DINOv2 ViT-S/14 (embed 384, 12 blocks))" in msg
    for frag in fragments:
        assert frag in msg, f"{frag!r} not in: {msg}"
    assert_unchanged(vit_s, before)
    assert torch.equal(vit_s.patch_pos, pos_before)


# ------------------------------------------------------------------------------ building and planning
@pytest.mark.parametrize("model", ["dinov2_vits14", "dinov2_vitg14", "dinov2_vitb14_reg4", "dinov2_vitl14_dav2"])
def test_plan_at_1080p_on_the_meta_device(model):
    cfg = load_config(
        {
            "input": {"height": 1080, "width": 1920},
            "foundation_model": {"model": model},
            "heads": [{"name": "depth", "model": "tiny_depth"}],
        }
    )
    plan = make_plan(cfg)
    c = {"s": 384, "b": 768, "l": 1024, "g": 1536}[model[len("dinov2_vit")]]
    assert plan.feature_meta["grid"] == (37, 66)
    assert plan.feature_meta["image_size"] == (518, 924)
    assert plan.feature_meta["embed_dim"] == c and plan.feature_meta["patch_size"] == 14
    assert plan.feature_meta["backbone"] == model
    assert plan.frame_spec["frame"] == TensorSpec((1080, 1920, 3), "uint8")
    for i in range(4):
        assert plan.features[f"patch.{i}"] == TensorSpec((37 * 66, c), "float32")
        assert plan.features[f"cls.{i}"] == TensorSpec((c,), "float32")
    assert len(plan.features) == 8
    assert all(p.device.type == "meta" for p in plan.foundation.parameters())
    assert plan.heads["depth"].output_spec == {"depth": TensorSpec((1080, 1920), "float32")}


def test_default_layers_and_checkpoints_of_the_recipes():
    expected = {"s": [2, 5, 8, 11], "b": [2, 5, 8, 11], "l": [4, 11, 17, 23], "g": [9, 19, 29, 39]}
    for size, layers in expected.items():
        for reg in (0, 4):
            model, _ = build_backbone(engine_cfg(recipe(size, reg), (518, 924)), "meta")
            assert model.layers == layers
            assert model.registers == reg
            assert model.default_checkpoint == f"dinov2_vit{size}14{'_reg4' if reg else ''}_pretrain"
    custom, _ = build_backbone(engine_cfg("dinov2_vits14", (140, 140), {**TINY, "depth": 6}), "meta")
    assert custom.layers == [0, 2, 3, 5] and custom.default_checkpoint is None


@pytest.mark.parametrize(("precision", "tol"), [("fp16", 2e-2), ("bf16", 1e-1)])
def test_reduced_precision_computes_and_declares_its_dtype(precision, tol):
    cfg32 = engine_cfg("dinov2_vits14", (140, 196), {**TINY})
    cfg = engine_cfg("dinov2_vits14", (140, 196), {**TINY}, precision=precision)
    m32, _ = build_backbone(cfg32)
    m, _ = build_backbone(cfg)
    dtype = {"fp16": torch.float16, "bf16": torch.bfloat16}[precision]
    assert all(p.dtype == dtype for p in m.parameters())
    img = image((140, 196))
    with torch.no_grad():
        out, ref = m({"image": img.to(dtype)}), m32({"image": img})
    for k, spec in m.output_spec.items():
        assert spec.dtype == {"fp16": "float16", "bf16": "bfloat16"}[precision]
        assert spec.matches(out[k][0]) and out[k].shape[0] == 1, k
        rel = ((out[k].float() - ref[k]).abs().max() / ref[k].abs().max()).item()
        assert rel < tol, (k, rel)


def test_random_weights_are_seeded_and_leave_the_global_rng_alone():
    torch.manual_seed(123)
    expected_next = torch.rand(1)
    torch.manual_seed(123)
    a = tiny_model((140, 140))
    assert torch.equal(torch.rand(1), expected_next)
    b = tiny_model((140, 140))
    c = tiny_model((140, 140), seed=7)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not torch.equal(sa["vit.blocks.0.attn.qkv.weight"], sc["vit.blocks.0.attn.qkv.weight"])


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"size": "custom", "embed_dim": 32}, "size 'custom' needs depth, heads"),
        (
            {"size": "custom", "embed_dim": 30, "depth": 4, "heads": 4},
            "embed_dim 30 is not divisible by heads 4",
        ),
        ({"embed_dim": 64}, "embed_dim only apply to size 'custom'; size 's' is the released ViT-S/14"),
        ({"layers": [2, 5, 8]}, r"layers \[2, 5, 8\] must be 4 increasing block indices from 0 to 11"),
        ({"layers": [2, 5, 11, 12]}, "must be 4 increasing block indices from 0 to 11"),
        ({"size": "xl"}, "size: Input should be 's', 'b', 'l', 'g' or 'custom'"),
        ({"pos_embed_interpolation": "timm"}, "pos_embed_interpolation: Input should be 'hf' or 'dinov2'"),
    ],
)
def test_bad_options_fail_with_the_value_and_what_is_accepted(options, message):
    cfg = engine_cfg("dinov2_vits14", (140, 140), options)
    with pytest.raises(ModelBuildError, match=message):
        build_backbone(cfg, "meta")


def test_outputs_match_the_declared_specs_and_registers_are_not_outputs():
    model = tiny_model((140, 196), registers=4)
    out = model(model.example_inputs())
    assert model.meta["grid"] == (10, 14) and model.meta["registers"] == 4
    check_outputs("foundation", model.output_spec, out, batch=1)
    assert model.output_spec["patch.0"] == TensorSpec((140, 32), "float32")
    assert model.output_spec["cls.0"] == TensorSpec((32,), "float32")
    assert model.input_spec == {"image": TensorSpec((3, 140, 196), "float32")}
