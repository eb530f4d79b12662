"""DINOv2 (ViT-S/B/L/G, patch 14, with or without registers) as a vpengine foundation model.

The network is timm's ``VisionTransformer`` in its DINOv2 configuration (``vit_*_patch14[_reg4]_dinov2``), built
without weights. vpengine adds what timm does not do for us:

* the engine's feature layout: four intermediate blocks, each after the final LayerNorm, exactly as DINOv2's
  ``get_intermediate_layers(x, n=layers, norm=True, return_class_token=True)``, as ``patch.0 .. patch.3``
  (``float[h*w, C]`` per frame, register tokens dropped) and ``cls.0 .. cls.3`` (``float[C]``), computed for a
  batch of frames at once (Note [Batched models] in base.py);
* position embeddings interpolated the way Hugging Face transformers does (see Note [position embedding
  interpolation]) and precomputed once for the engine's fixed input size;
* checkpoint loading from the official files in every layout they ship in (facebookresearch ``*_pretrain.pth``,
  Hugging Face ``facebook/dinov2-*`` safetensors, the encoder inside Depth-Anything-V2 ``.pth`` files, timm), with
  the layout detected from the keys and applied strictly (all or nothing).

Key layouts (``C`` = embed dim, ``M`` = 37 position-grid side for the 518-pixel pretraining size):

=====================  ==========================================  ================================================
what                   official (facebookresearch/dinov2)          Hugging Face (``facebook/dinov2-*``)
=====================  ==========================================  ================================================
class token            ``cls_token`` [1,1,C]                       ``embeddings.cls_token``
position embedding     ``pos_embed`` [1,1+M*M,C] (class first)     ``embeddings.position_embeddings``
registers              ``register_tokens`` [1,R,C]                 ``embeddings.register_tokens``
patch embedding        ``patch_embed.proj.{weight,bias}``          ``embeddings.patch_embeddings.projection.*``
attention              ``blocks.N.attn.qkv`` (q,k,v stacked)       ``encoder.layer.N.attention.attention.{query,
                                                                   key,value}``
attention output       ``blocks.N.attn.proj``                      ``encoder.layer.N.attention.output.dense``
layer scale            ``blocks.N.ls{1,2}.gamma``                  ``encoder.layer.N.layer_scale{1,2}.lambda1``
MLP                    ``blocks.N.mlp.fc{1,2}``                    ``encoder.layer.N.mlp.fc{1,2}``
SwiGLU MLP (giant)     ``blocks.N.mlp.w12`` / ``mlp.w3``           ``encoder.layer.N.mlp.weights_in/weights_out``
final norm             ``norm``                                    ``layernorm``
=====================  ==========================================  ================================================

Depth-Anything-V2 files hold the official layout under ``pretrained.`` next to ``depth_head.*``. timm's own layout
(this model's ``state_dict``) is the official one without ``mask_token``, with ``mlp.fc1/fc2`` for SwiGLU, and, for
register models, ``reg_token`` and a class token that already includes its position embedding (see
:func:`convert_official_to_timm`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import torch
import torch.nn.functional as F
from pydantic import Field, model_validator

from vpengine.models.base import BuildContext, Model, ModelBuildError, Options, Pipeline
from vpengine.models.preprocess import ImagePreprocess
from vpengine.models.tiny import N_LAYERS, feature_specs
from vpengine.models.weights import (
    CheckpointError,
    apply_state_dict,
    configured_or_default,
    read_state_dict,
    resolve_checkpoint,
)
from vpengine.specs import TensorSpec

if TYPE_CHECKING:
    from vpengine.config import ModelConfig

PATCH_SIZE = 14
#: The pretraining resolution of every released DINOv2: a 37 x 37 position grid.
PRETRAIN_SIZE = 518

Layout = Literal["official", "dav2", "hf", "timm"]
PosInterpolation = Literal["hf", "dinov2"]


@dataclass(frozen=True)
class Arch:
    """One released DINOv2 size."""

    title: str
    timm_name: str  # without registers; the ``_reg4_`` variant is derived from it
    embed_dim: int
    depth: int
    heads: int
    swiglu: bool
    #: The four blocks Depth-Anything-V2 reads (``intermediate_layer_idx``); our default feature layers.
    layers: tuple[int, int, int, int]


ARCHS: dict[str, Arch] = {
    "s": Arch("ViT-S/14", "vit_small_patch14_dinov2", 384, 12, 6, False, (2, 5, 8, 11)),
    "b": Arch("ViT-B/14", "vit_base_patch14_dinov2", 768, 12, 12, False, (2, 5, 8, 11)),
    "l": Arch("ViT-L/14", "vit_large_patch14_dinov2", 1024, 24, 16, False, (4, 11, 17, 23)),
    "g": Arch("ViT-G/14", "vit_giant_patch14_dinov2", 1536, 40, 24, True, (9, 19, 29, 39)),
}

_CUSTOM_ONLY = ("embed_dim", "depth", "heads", "mlp_ratio", "swiglu", "pretrain_size")


def swiglu_hidden(embed_dim: int, mlp_ratio: float = 4.0) -> int:
    """Hidden width of DINOv2's SwiGLU MLP: two thirds of the plain MLP's, rounded up to a multiple of 8
    (1536 -> 4096 for ViT-G). Same formula in facebookresearch/dinov2 and Hugging Face."""
    return (int(int(embed_dim * mlp_ratio) * 2 / 3) + 7) // 8 * 8


def default_layers(depth: int) -> list[int]:
    """Four blocks evenly spread over ``depth``, the last one last (12 -> [2, 5, 8, 11])."""
    return [(i + 1) * depth // N_LAYERS - 1 for i in range(N_LAYERS)]


class DinoV2Options(Options):
    """Options of every ``dinov2_*`` recipe (the recipe presets ``size``, ``registers`` and the checkpoint name)."""

    size: Literal["s", "b", "l", "g", "custom"] = Field(
        "s",
        description="s | b | l | g (the released ViT-S/B/L/G/14), or custom (set embed_dim, depth, heads).",
    )
    registers: int = Field(0, ge=0, le=64, description="Register tokens (4 for the *_reg4 releases).")
    layers: list[int] | None = Field(
        None,
        description="The four blocks (0-based, shallow to deep) whose normed outputs are patch.0..3 / cls.0..3; "
        "null: [2,5,8,11] for S and B, [4,11,17,23] for L, [9,19,29,39] for G, evenly spread for custom.",
    )
    pos_embed_interpolation: PosInterpolation = Field(
        "hf",
        description="hf: as Hugging Face transformers (bicubic to the grid size; antialiased with registers); "
        "dinov2: as facebookresearch/dinov2 and Depth-Anything-V2 (models without registers use a +0.1 "
        "scale-factor offset, no antialias).",
    )
    default_checkpoint: str | None = Field(
        None, description="Catalog name loaded when the config's checkpoint is null (set by the recipe)."
    )
    seed: int = Field(0, description="Seed of the random initial weights (identical in every process).")
    embed_dim: int | None = Field(None, ge=8, le=8192, description="custom: embedding width.")
    depth: int | None = Field(None, ge=N_LAYERS, le=256, description="custom: number of blocks.")
    heads: int | None = Field(None, ge=1, le=256, description="custom: attention heads (divides embed_dim).")
    mlp_ratio: float | None = Field(None, gt=0, le=16, description="custom: MLP width / embed_dim (default 4).")
    swiglu: bool | None = Field(None, description="custom: SwiGLU MLP as in ViT-G (default false).")
    pretrain_size: int | None = Field(
        None,
        ge=PATCH_SIZE,
        le=8192,
        description="custom: side of the square position-embedding grid in pixels "
        "(default 518, i.e. 37 x 37 like every release).",
    )

    @model_validator(mode="after")
    def _check(self) -> DinoV2Options:
        if self.size == "custom":
            missing = [k for k in ("embed_dim", "depth", "heads") if getattr(self, k) is None]
            if missing:
                raise ValueError(f"size 'custom' needs {', '.join(missing)} (got {self.model_dump()})")
            assert self.embed_dim is not None and self.heads is not None
            if self.embed_dim % self.heads:
                raise ValueError(f"embed_dim {self.embed_dim} is not divisible by heads {self.heads}")
        else:
            given = [k for k in _CUSTOM_ONLY if getattr(self, k) is not None]
            if given:
                raise ValueError(
                    f"{', '.join(given)} only apply to size 'custom'; size {self.size!r} is the released "
                    f"{ARCHS[self.size].title}"
                )
        depth = self.depth if self.size == "custom" else ARCHS[self.size].depth
        assert depth is not None
        if self.layers is not None:
            ok = (
                len(self.layers) == N_LAYERS
                and all(0 <= i < depth for i in self.layers)
                and all(a < b for a, b in zip(self.layers, self.layers[1:]))
            )
            if not ok:
                raise ValueError(
                    f"layers {self.layers} must be {N_LAYERS} increasing block indices from 0 to {depth - 1}"
                )
        return self


# ---------------------------------------------------------------------------------------------- key conversion
_HF_PREFIXES = ("", "dinov2.", "backbone.")
_DAV2_PREFIX = "pretrained."


def detect_layout(sd: Mapping[str, Any]) -> tuple[Layout, str] | None:
    """The key layout of a DINOv2 state dict and the prefix its encoder lives under, or None if unrecognised.

    ``official``: facebookresearch ``*_pretrain.pth`` (and timm without registers, which is identical);
    ``dav2``: Depth-Anything-V2 ``.pth`` (official layout under ``pretrained.``); ``hf``: Hugging Face Dinov2 /
    Dinov2WithRegisters, bare or under ``dinov2.`` / ``backbone.`` (classifier, Depth-Anything ports); ``timm``:
    timm's register models (``reg_token``).
    """
    if "reg_token" in sd and "cls_token" in sd:
        return "timm", ""
    if "cls_token" in sd and "pos_embed" in sd:
        return "official", ""
    if f"{_DAV2_PREFIX}cls_token" in sd and f"{_DAV2_PREFIX}pos_embed" in sd:
        return "dav2", _DAV2_PREFIX
    for prefix in _HF_PREFIXES:
        if f"{prefix}embeddings.cls_token" in sd and f"{prefix}embeddings.position_embeddings" in sd:
            return "hf", prefix
    return None


def convert_dav2_to_official(sd: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The DINOv2 encoder of a Depth-Anything-V2 checkpoint (``pretrained.*``), in the official layout.
    Every other key (``depth_head.*``) is left out: it belongs to the DPT head."""
    n = len(_DAV2_PREFIX)
    return {k[n:]: v for k, v in sd.items() if k.startswith(_DAV2_PREFIX)}


# transformers >= 5 renames modules in memory (q_proj, gate_proj, ...) but keeps the hub names on disk; both are
# accepted so that a torch.save(model.state_dict()) of a current HF model loads as well as a hub file.
_HF_RENAMES = [
    (re.compile(r"^embeddings\.cls_token$"), "cls_token"),
    (re.compile(r"^embeddings\.mask_token$"), "mask_token"),
    (re.compile(r"^embeddings\.position_embeddings$"), "pos_embed"),
    (re.compile(r"^embeddings\.register_tokens$"), "register_tokens"),
    (re.compile(r"^embeddings\.patch_embeddings\.projection\."), "patch_embed.proj."),
    (re.compile(r"^layernorm\."), "norm."),
    (re.compile(r"^encoder\.layer\.(\d+)\.norm([12])\."), r"blocks.\1.norm\2."),
    (re.compile(r"^encoder\.layer\.(\d+)\.attention\.(?:output\.dense|o_proj)\."), r"blocks.\1.attn.proj."),
    (re.compile(r"^encoder\.layer\.(\d+)\.layer_scale([12])\.lambda1$"), r"blocks.\1.ls\2.gamma"),
    (re.compile(r"^encoder\.layer\.(\d+)\.mlp\.fc([12])\."), r"blocks.\1.mlp.fc\2."),
    (re.compile(r"^encoder\.layer\.(\d+)\.mlp\.weights_in\."), r"blocks.\1.mlp.w12."),
    (re.compile(r"^encoder\.layer\.(\d+)\.mlp\.(?:weights_out|down_proj)\."), r"blocks.\1.mlp.w3."),
]
_HF_QKV = re.compile(
    r"^encoder\.layer\.(\d+)\.attention\.(?:attention\.(query|key|value)|([qkv])_proj)\.(weight|bias)$"
)
_HF_GATE_UP = re.compile(r"^encoder\.layer\.(\d+)\.mlp\.(gate|up)_proj\.(weight|bias)$")


def convert_hf_to_official(sd: Mapping[str, torch.Tensor], prefix: str = "") -> dict[str, torch.Tensor]:
    """A Hugging Face Dinov2(WithRegisters) state dict (keys under ``prefix``) in the official layout.

    Separate query/key/value projections are stacked into ``attn.qkv`` (q, k, v order, as the official fused
    projection). Keys that do not belong to the encoder or that cannot be converted (a layer missing one of q/k/v)
    are kept under their original name, so a strict load reports them instead of dropping them silently.
    """
    out: dict[str, torch.Tensor] = {}
    pending: dict[tuple[str, str, str], dict[str, torch.Tensor]] = {}
    pending_names: dict[tuple[str, str, str], list[str]] = {}
    n = len(prefix)
    for full, v in sd.items():
        if not full.startswith(prefix):
            continue  # the rest of a larger model (classifier, neck, head)
        k = full[n:]
        m = _HF_QKV.match(k)
        if m:
            which = {"query": "q", "key": "k", "value": "v"}.get(m.group(2) or "", m.group(3))
            pending.setdefault((m.group(1), "qkv", m.group(4)), {})[which] = v
            pending_names.setdefault((m.group(1), "qkv", m.group(4)), []).append(k)
            continue
        m = _HF_GATE_UP.match(k)
        if m:
            pending.setdefault((m.group(1), "w12", m.group(3)), {})[m.group(2)] = v
            pending_names.setdefault((m.group(1), "w12", m.group(3)), []).append(k)
            continue
        for pattern, repl in _HF_RENAMES:
            if pattern.search(k):
                k = pattern.sub(repl, k)
                break
        out[k] = v
    for (layer, kind, param), parts in pending.items():
        order = ("q", "k", "v") if kind == "qkv" else ("gate", "up")
        if set(parts) != set(order):
            for name in pending_names[(layer, kind, param)]:
                out[name] = sd[prefix + name]
            continue
        target = f"blocks.{layer}.attn.qkv.{param}" if kind == "qkv" else f"blocks.{layer}.mlp.w12.{param}"
        out[target] = torch.cat([parts[p] for p in order], 0)
    return out


def convert_official_to_timm(sd: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """An official-layout DINOv2 state dict in timm's layout (this model's own keys).

    Follows timm's own DINOv2 filter (``timm.models.vision_transformer._convert_dinov2``), re-implemented because
    that function is private and pops from its input: ``mask_token`` (training only) is dropped, SwiGLU
    ``w12``/``w3`` become ``fc1``/``fc2`` (timm's packed SwiGLU has the same gate-first order), and for register
    models, which timm builds with position embeddings for patches only, the class token absorbs its position
    embedding (``cls + pos[:, 0]``, exactly what DINOv2 adds in its forward) and ``register_tokens`` becomes
    ``reg_token``.
    """
    out = {k: v for k, v in sd.items() if k != "mask_token"}
    for k in list(out):
        m = re.match(r"^(blocks\.\d+\.mlp\.)(w12|w3)\.(weight|bias)$", k)
        if m:
            out[f"{m.group(1)}{'fc1' if m.group(2) == 'w12' else 'fc2'}.{m.group(3)}"] = out.pop(k)
    if "register_tokens" in out and "cls_token" in out and "pos_embed" in out:
        pos, cls = out["pos_embed"], out["cls_token"]
        out["reg_token"] = out.pop("register_tokens")
        out["cls_token"] = (cls.float() + pos[:, :1].float()).to(cls.dtype)
        out["pos_embed"] = pos[:, 1:]
    return out


def convert_to_timm(sd: Mapping[str, torch.Tensor]) -> tuple[Layout | None, dict[str, torch.Tensor]]:
    """Detect the layout of ``sd`` and convert it to timm's (this model's) keys.
    An unrecognised layout is returned unchanged with layout None (a strict load then names its keys)."""
    found = detect_layout(sd)
    if found is None:
        return None, dict(sd)
    layout, prefix = found
    if layout == "timm":
        return layout, dict(sd)
    if layout == "dav2":
        official = convert_dav2_to_official(sd)
    elif layout == "hf":
        official = convert_hf_to_official(sd, prefix)
    else:
        official = dict(sd)
    return layout, convert_official_to_timm(official)


# ------------------------------------------------------------------------------------------------------ model
# Note [position embedding interpolation]
# DINOv2 learns a 37 x 37 grid of patch position embeddings (518-pixel pretraining). At another input size the
# grid is resampled, and the references disagree on how, by amounts that matter (up to ~0.4 on unit-scale
# embeddings at 37 x 66):
#   * Hugging Face Dinov2: bicubic, align_corners=False, to the exact grid size, in float32, no antialias;
#     Dinov2WithRegisters: the same with antialias=True. Both skip resampling for a square input of the native grid.
#   * facebookresearch/dinov2 hub models and Depth-Anything-V2: without registers, bicubic with
#     scale_factor=(grid + 0.1) / 37 (an old floating-point workaround; the kernel then samples at slightly
#     different positions) and no antialias; with registers, size=grid and antialias=True, as HF.
#   * timm (dynamic_img_size): bicubic with antialias=True for every model, re-run on every forward.
# We follow Hugging Face by default (option "dinov2" reproduces the original repositories). Because an engine's
# input size is fixed, the resampled embedding depends only on the weights: it is computed once at build and after
# every state-dict load, and the forward adds a constant. That is exact (the same float32 computation the
# references do per call) and saves the resampling on every frame (measured on one CPU core at 37 x 66: ~10 ms
# for ViT-S, ~47 ms for ViT-G). The class token's position embedding is folded into the constant prefix the same
# way.


def resample_patch_pos(
    pos: torch.Tensor, grid: tuple[int, int], antialias: bool, offset: float | None = None
) -> torch.Tensor:
    """Resample patch position embeddings ``[1, M*M, C]`` to ``[1, gh*gw, C]`` (bicubic, in float32).

    ``offset`` None: to the exact size (Hugging Face); a number: with ``scale_factor=(g + offset) / M`` as the
    original DINOv2 code. A square grid of the native size is returned unchanged, as both references do.
    """
    n, dim = pos.shape[1], pos.shape[2]
    side = math.isqrt(n)
    if side * side != n:
        raise ValueError(f"position embedding has {n} patch entries, which is not a square grid")
    if grid == (side, side):
        return pos
    x = pos.float().reshape(1, side, side, dim).permute(0, 3, 1, 2)
    if offset is None:
        x = F.interpolate(x, size=grid, mode="bicubic", align_corners=False, antialias=antialias)
    else:
        scale = ((grid[0] + offset) / side, (grid[1] + offset) / side)
        x = F.interpolate(x, scale_factor=scale, mode="bicubic", align_corners=False, antialias=antialias)
        if tuple(x.shape[-2:]) != grid:  # cannot happen for offset < 1, but never add a misshapen grid
            raise ValueError(f"scale-factor resampling gave {tuple(x.shape[-2:])}, expected {grid}")
    return x.permute(0, 2, 3, 1).reshape(1, grid[0] * grid[1], dim).to(pos.dtype)


class DinoV2(Model):
    """DINOv2 backbone: ``image: float[3, h, w]`` (normalised, h and w multiples of 14) -> ``patch.0..3``
    ``float[(h/14)*(w/14), C]`` and ``cls.0..3`` ``float[C]``, in the model dtype, per frame of a batch.

    Build it through :meth:`from_config` (it prepends :class:`ImagePreprocess`). ``meta`` holds ``grid``,
    ``embed_dim``, ``patch_size``, ``layers``, ``backbone`` (the recipe name), ``image_size`` and ``registers``.
    """

    role = "foundation"

    def __init__(
        self,
        image_hw: tuple[int, int],
        opts: DinoV2Options,
        dtype: str = "float32",
        backbone: str = "dinov2",
    ) -> None:
        super().__init__()
        import timm  # heavy import, only where a DINOv2 is built

        h, w = image_hw
        if h % PATCH_SIZE or w % PATCH_SIZE or h <= 0 or w <= 0:
            raise ModelBuildError(f"DINOv2 input {h}x{w} must be positive multiples of the patch size {PATCH_SIZE}")
        self.opts = opts
        self.registers = opts.registers
        self.grid = (h // PATCH_SIZE, w // PATCH_SIZE)
        name, kwargs, self.title, depth = self._timm_args(opts)
        self.layers = list(opts.layers) if opts.layers is not None else self._default_layers(opts, depth)
        self.default_checkpoint = opts.default_checkpoint if opts.size != "custom" else None
        if opts.pos_embed_interpolation == "dinov2" and not self.registers:
            self._pos_offset: float | None = 0.1
        else:
            self._pos_offset = None

        # Seeded so that every process building this recipe gets the same random weights (thread and process
        # mode then give the same outputs); fork_rng keeps the caller's RNG streams untouched.
        device = torch.get_default_device()
        rng_devices = [device.index or 0] if device.type == "cuda" else []
        with torch.random.fork_rng(devices=rng_devices):
            torch.manual_seed(opts.seed)
            # num_classes=0 and global_pool='' leave no head: the state dict is exactly the encoder's.
            self.vit = timm.create_model(
                name, pretrained=False, num_classes=0, global_pool="", dynamic_img_size=True, **kwargs
            )
        self.vit.to(TensorSpec((), dtype).torch_dtype)
        self.embed_dim = int(self.vit.embed_dim)
        self._prefix_len = 1 + self.registers
        # See Note [position embedding interpolation]: constants of the forward, never saved in a state dict.
        self.register_buffer("prefix_tokens", torch.empty(0), persistent=False)
        self.register_buffer("patch_pos", torch.empty(0), persistent=False)
        self.refresh_position_cache()
        # A module-level hook that receives the module (not a closure over self): it stays right under deepcopy.
        self.register_load_state_dict_post_hook(_refresh_after_load)

        self.input_spec = {"image": TensorSpec((3, h, w), dtype)}
        self.output_spec = feature_specs(self.grid[0] * self.grid[1], self.embed_dim, dtype)
        self.meta = {
            "grid": self.grid,
            "embed_dim": self.embed_dim,
            "patch_size": PATCH_SIZE,
            "layers": self.layers,
            # what the recipe's released heads were trained on (Note [Trained layers] in runtime/plan.py)
            "default_layers": self._default_layers(opts, depth),
            "backbone": backbone,
            "image_size": (h, w),
            "registers": self.registers,
        }

    # -- construction ---------------------------------------------------------------------------------------
    @staticmethod
    def _timm_args(opts: DinoV2Options) -> tuple[str, dict[str, Any], str, int]:
        """timm model name and overrides, a title for messages, and the depth."""
        reg = opts.registers
        if opts.size != "custom":
            arch = ARCHS[opts.size]
            name = arch.timm_name.replace("_dinov2", "_reg4_dinov2") if reg else arch.timm_name
            kwargs: dict[str, Any] = {"img_size": PRETRAIN_SIZE}
            if reg:
                kwargs["reg_tokens"] = reg
            title = f"DINOv2 {arch.title}" + (f" with {reg} registers" if reg else "")
            return name, kwargs, title, arch.depth
        assert opts.embed_dim is not None and opts.depth is not None and opts.heads is not None
        swiglu = bool(opts.swiglu)
        ratio = opts.mlp_ratio if opts.mlp_ratio is not None else 4.0
        # The giant variant carries SwiGLU (packed, SiLU), the small one the plain GELU MLP; every size-defining
        # argument is overridden.
        name = "vit_giant_patch14_dinov2" if swiglu else "vit_small_patch14_dinov2"
        if reg:
            name = name.replace("_dinov2", "_reg4_dinov2")
        kwargs = {
            "img_size": opts.pretrain_size or PRETRAIN_SIZE,
            "embed_dim": opts.embed_dim,
            "depth": opts.depth,
            "num_heads": opts.heads,
        }
        if reg:
            kwargs["reg_tokens"] = reg
        if swiglu:
            # timm sizes the packed w12 projection as int(dim * mlp_ratio) = 2 * hidden; the +0.5 keeps the
            # float product from rounding down below it.
            kwargs["mlp_ratio"] = (2 * swiglu_hidden(opts.embed_dim, ratio) + 0.5) / opts.embed_dim
        else:
            kwargs["mlp_ratio"] = ratio
        title = (
            f"DINOv2 custom (embed {opts.embed_dim}, {opts.depth} blocks, {opts.heads} heads"
            + (", SwiGLU" if swiglu else "")
            + (f", {reg} registers" if reg else "")
            + ")"
        )
        return name, kwargs, title, opts.depth

    @staticmethod
    def _default_layers(opts: DinoV2Options, depth: int) -> list[int]:
        return list(ARCHS[opts.size].layers) if opts.size != "custom" else default_layers(depth)

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        opts = ctx.options(DinoV2Options)
        h, w = ctx.input_hw
        pre = ImagePreprocess(
            h,
            w,
            ctx.engine.foundation_model.preprocess,
            PATCH_SIZE,
            ctx.engine.input.color,
            ctx.engine.input.dtype,
            ctx.dtype_name,
        )
        return Pipeline(pre, cls(pre.size, opts, ctx.dtype_name, backbone=ctx.cfg.model))

    def describe(self) -> str:
        """What this model is, for messages: ``DINOv2 ViT-S/14 (embed 384, 12 blocks)``."""
        return f"{self.title} (embed {self.embed_dim}, {len(self.vit.blocks)} blocks)"

    # -- position embeddings --------------------------------------------------------------------------------
    @torch.no_grad()
    def refresh_position_cache(self) -> None:
        """Recompute the constant prefix tokens and resampled patch position embeddings from the weights.
        Runs at build, after :meth:`load_state_dict_any` and after ``load_state_dict`` of this model (a post-hook);
        call it yourself after changing ``self.vit``'s weights directly (Note [position embedding interpolation])."""
        vit = self.vit
        pos = vit.pos_embed
        if self.registers:
            # timm register layout: pos_embed covers patches only; the class token already holds its position.
            patch_pos = pos
            prefix = torch.cat([vit.cls_token, vit.reg_token], 1)
        else:
            patch_pos = pos[:, 1:]
            prefix = (vit.cls_token.float() + pos[:, :1].float()).to(pos.dtype)
        self.prefix_tokens = prefix.detach().clone()
        self.patch_pos = resample_patch_pos(
            patch_pos.detach(), self.grid, antialias=self.registers > 0, offset=self._pos_offset
        ).clone()

    # -- weights --------------------------------------------------------------------------------------------
    def load_state_dict_any(self, sd: Mapping[str, torch.Tensor], source: str, expected: str | None = None) -> str:
        """Load a DINOv2 state dict in any supported layout, strictly and all or nothing; returns the layout.

        ``source`` (the file) and ``expected`` (the model it was meant for) appear in every error, with the
        missing, unexpected or misshapen keys (named after conversion to this model's keys).
        """
        expected = expected or self.describe()
        layout, converted = convert_to_timm(sd)
        try:
            apply_state_dict(self.vit, converted, source, expected)  # checks every key first: all or nothing
        except CheckpointError as e:
            if layout is None:
                raise CheckpointError(
                    f"{e}; no DINOv2 key layout was recognised (official/Depth-Anything-V2 'pretrained.'/Hugging "
                    f"Face 'embeddings.*'/timm); the file's keys: {_preview(sorted(sd))}"
                ) from None
            raise CheckpointError(f"{e} (file layout: {layout}; it holds {_summarize(converted)})") from None
        self.refresh_position_cache()
        return layout or "timm"  # keys this model accepted without conversion are timm's

    def needed_checkpoint(self, cfg: ModelConfig) -> str | None:
        return configured_or_default(cfg, self.default_checkpoint)

    def load_checkpoint(self, ctx: BuildContext) -> None:
        """Load ``ctx.cfg.checkpoint`` (file or catalog name), else the recipe's default; nothing when random."""
        path = resolve_checkpoint(ctx, self)
        if path is None:
            return
        expected = f"{ctx.name} ({ctx.cfg.model}: {self.describe()})"
        try:
            sd = read_state_dict(path)
        except CheckpointError as e:
            raise CheckpointError(f"{e} (needed by {expected})") from None
        self.load_state_dict_any(sd, str(path), expected)

    # -- forward --------------------------------------------------------------------------------------------
    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        vit = self.vit
        x = vit.patch_embed(inputs["image"])  # [B, gh, gw, C] (dynamic_img_size defers the flatten)
        b = x.shape[0]
        x = x.flatten(1, 2) + self.patch_pos
        x = torch.cat([self.prefix_tokens.expand(b, -1, -1), x], 1)
        out: dict[str, torch.Tensor] = {}
        take = {layer: k for k, layer in enumerate(self.layers)}
        # Blocks after the deepest requested layer are skipped: their outputs would be discarded.
        for i in range(self.layers[-1] + 1):
            x = vit.blocks[i](x)
            k = take.get(i)
            if k is not None:
                y = vit.norm(x)
                out[f"patch.{k}"] = y[:, self._prefix_len :].contiguous()
                out[f"cls.{k}"] = y[:, 0].contiguous()
        return out


def _refresh_after_load(module: torch.nn.Module, _incompatible: Any) -> None:
    assert isinstance(module, DinoV2)
    module.refresh_position_cache()


def _summarize(sd: Mapping[str, torch.Tensor]) -> str:
    """What a converted state dict is, from its shapes: 'a DINOv2 with embed 768, 12 blocks, 0 registers'."""
    cls = sd.get("cls_token")
    if cls is None:
        return "no class token"
    blocks = {int(m.group(1)) for k in sd if (m := re.match(r"^blocks\.(\d+)\.", k))}
    reg = sd.get("reg_token")
    return f"a DINOv2 with embed {cls.shape[-1]}, {len(blocks)} blocks, {0 if reg is None else reg.shape[1]} registers"


def _preview(keys: list[str], n: int = 8) -> str:
    return ", ".join(keys[:n]) + (f", ... ({len(keys)} in all)" if len(keys) > n else "")
