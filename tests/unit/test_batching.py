"""A batch of frames gives, frame by frame, what each frame gives alone (Note [Batched models] in models/base.py,
Note [Executor contract] in backends/base.py): every model of the zoo called directly, and every backend that runs
on the CPU (eager, torch.compile, ONNX Runtime) on the tiny pipeline.

Float outputs are compared relative to the output's largest magnitude: batched kernels may sum in another order than
single-frame ones, nothing more. Integer maps quantise floats (class ids, colour-mapped depth), so a near-tie may flip
a few pixels (at most 0.1%); short integer outputs (labels, counts) must be equal.
"""

from __future__ import annotations

import contextlib
import logging

import numpy as np
import pytest
import torch

from helpers.frames import frame
from helpers.groups import INDUCTOR
from tests_paths import tiny
from vpengine.backends import BackendError, make_executor
from vpengine.config import PreprocessConfig, load_config
from vpengine.models.base import Model, check_outputs
from vpengine.models.build import build_model
from vpengine.models.preprocess import ImagePreprocess, exact_preprocessing
from vpengine.runtime.plan import make_plan
from vpengine.specs import TensorSpec

pytestmark = pytest.mark.timeout(600)

CPU = torch.device("cpu")
B = 3
#: Integer outputs with more elements than this are maps (see the module docstring).
MAP_SIZE = 1000
#: Tiny DPT widths: the released head's structure at a size that runs in milliseconds.
DPT_WIDTHS = {"features": 16, "out_channels": [8, 16, 32, 32]}
#: A DINOv2 of the released structure (timm ViT, registers, four intermediate layers), 32 wide and 4 deep.
SMALL_DINOV2 = {
    "model": "dinov2_vits14",
    "options": {"size": "custom", "embed_dim": 32, "depth": 4, "heads": 2, "registers": 4},
    "preprocess": {"size": 56},
}


@pytest.fixture(autouse=True)
def one_thread():
    # As in a worker (cpu_threads: 1): deterministic float results and no oversubscription of the CI machine.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def zoo_config(foundation: dict, heads: list[dict]) -> object:
    return load_config(
        {
            "mode": "thread",
            "input": {"height": 70, "width": 100},
            "weights": {"random_weights": True},
            "foundation_model": foundation,
            "heads": heads,
        }
    )


def build(cfg, name: str) -> Model:
    plan = make_plan(cfg)
    if name == "foundation":
        return build_model(cfg, name, "foundation", plan.frame_spec, {}, CPU, plan_only=False)
    return build_model(cfg, name, "head", plan.features, plan.feature_meta, CPU, plan_only=False)


def frames_of(cfg, n: int = B) -> list[dict[str, torch.Tensor]]:
    """``n`` different frames of the config's input size, each a batch of one."""
    return [{"frame": torch.from_numpy(frame(i, cfg.input.height, cfg.input.width))[None]} for i in range(n)]


def features_of(cfg, model: Model, n: int = B) -> list[dict[str, torch.Tensor]]:
    """What ``model`` (a head) reads for ``n`` different frames, each a batch of one (the eager backbone's)."""
    fm = build(cfg, "foundation")
    with torch.inference_mode():
        return [{k: v for k, v in fm(x).items() if k in model.input_spec} for x in frames_of(cfg, n)]


def cat(inputs: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    return {k: torch.cat([x[k] for x in inputs]) for k in inputs[0]}


def assert_batch_is_its_frames(
    together: dict[str, torch.Tensor], alone: list[dict[str, torch.Tensor]], rtol: float, what: str
) -> None:
    """Frame ``i`` of the batched outputs equals the outputs of frame ``i`` run as a batch of one."""
    assert set(together) == set(alone[0]), what
    for k, t in together.items():
        assert t.shape[0] == len(alone), f"{what}: {k}: {list(t.shape)} for {len(alone)} frames"
        for i, single in enumerate(alone):
            got, want = t[i], single[k][0]
            assert got.dtype == want.dtype and got.shape == want.shape, f"{what}: {k}, frame {i}"
            if want.dtype.is_floating_point:
                scale = want.float().abs().max().item()
                torch.testing.assert_close(
                    got, want, rtol=rtol, atol=rtol * scale, msg=lambda m, k=k, i=i: f"{what}: {k}, frame {i}: {m}"
                )
            elif want.numel() > MAP_SIZE:  # a class or colour map: quantised floats, a near-tie may flip
                share = (got != want).double().mean().item()
                assert share <= 1e-3, f"{what}: {k}, frame {i}: {share:.3%} of elements differ"
            else:
                assert torch.equal(got, want), f"{what}: {k}, frame {i}: {(got != want).sum().item()} differ"


def assert_frames_differ(outputs: dict[str, torch.Tensor], what: str) -> None:
    """The frames gave different outputs: a test of per-frame results must not pass on a broadcast frame 0."""
    assert any(not torch.equal(v[0], v[1]) for v in outputs.values()), f"{what}: frames 0 and 1 gave the same"


def check_model(model: Model, inputs: list[dict[str, torch.Tensor]], what: str, rtol: float = 1e-5) -> None:
    with torch.inference_mode():
        together = model(cat(inputs))
        alone = [model(x) for x in inputs]
    check_outputs(what, model.output_spec, together, batch=len(inputs))
    assert_batch_is_its_frames(together, alone, rtol, what)
    assert_frames_differ(together, what)


# ------------------------------------------------------------------------------------------ every model
@pytest.mark.parametrize(
    ("hw", "resize", "in_dtype", "exact"),
    [
        ((270, 480), "aspect", "uint8", False),  # the CPU's 8-bit fast path
        ((270, 480), "aspect", "uint8", True),  # the float path GPUs and ONNX exports take
        ((270, 480), "square", "float32", False),  # float frames
        ((100, 150), "none", "uint8", False),  # cropped, not resized
    ],
    ids=["uint8-fast", "uint8-exact", "float32-square", "crop"],
)
def test_preprocess_batches_every_path(hw, resize, in_dtype, exact):
    pre = ImagePreprocess(*hw, PreprocessConfig(resize=resize, size=112), 14, in_dtype=in_dtype)
    frames = [torch.from_numpy(frame(i, *hw))[None] for i in range(B)]
    if in_dtype == "float32":
        frames = [f.float() / 255 for f in frames]
    if exact:
        with exact_preprocessing():
            check_model(pre, [{"frame": f} for f in frames], "preprocess")
    else:
        check_model(pre, [{"frame": f} for f in frames], "preprocess")


@pytest.mark.parametrize("name", ["foundation", "depth", "seg", "det"])
def test_tiny_models_batch(name):
    cfg = tiny("thread")
    model = build(cfg, name)
    inputs = frames_of(cfg) if name == "foundation" else features_of(cfg, model)
    check_model(model, inputs, f"tiny {name}")


def test_dinov2_with_registers_batches():
    cfg = zoo_config(SMALL_DINOV2, [])
    check_model(build(cfg, "foundation"), frames_of(cfg), "dinov2")


@pytest.mark.parametrize(
    "head",
    [
        {"name": "h", "model": "dav2_depth_s", "options": DPT_WIDTHS, "postprocess": {"output": "both"}},
        {"name": "h", "model": "dav2_depth_s", "options": {**DPT_WIDTHS, "use_clstoken": True, "use_bn": True}},
        {"name": "h", "model": "dinov2_linear_ade20k_s", "options": {"upsample": "torch"}},
        {
            "name": "h",
            "model": "frcnn_dinov2_lite",
            "options": {"num_classes": 3, "score_threshold": 0.0, "max_detections": 1000},
        },
    ],
    ids=["dpt-colormap", "dpt-clstoken", "linear-seg", "faster-rcnn"],
)
def test_heads_of_the_zoo_batch(head):
    cfg = zoo_config(SMALL_DINOV2, [head])
    model = build(cfg, "h")
    inputs = features_of(cfg, model)
    check_model(model, inputs, head["model"], rtol=1e-4)
    if head["model"].startswith("frcnn"):  # a count per frame, and they differ: no frame sees another's boxes
        with torch.inference_mode():
            counts = model(cat(inputs))["count"]
        assert counts.shape == (B,) and len(set(counts.tolist())) > 1, counts


# ------------------------------------------------------------------------------------------ every backend
def tiny_inputs(cfg, name: str, model: Model, n: int = B) -> list[dict[str, torch.Tensor]]:
    return frames_of(cfg, n) if name == "foundation" else features_of(cfg, model, n)


@pytest.mark.parametrize("backend", ["eager", pytest.param("compile", marks=INDUCTOR), "onnx"])
@pytest.mark.parametrize("name", [pytest.param("foundation", marks=pytest.mark.slow), "depth", "seg", "det"])
def test_backends_run_a_batch_as_its_frames_alone(backend, name, tmp_path):
    b = B  # batches of 2 and 3 share one compiled graph (Note [One compile for every batch])
    cfg = tiny("thread")
    model = build(cfg, name)
    inputs = tiny_inputs(cfg, name, model, b)
    # inputs of both kinds: inference tensors (the last frame, and every frame of a head's features) and plain ones
    # (the batches, and the foundation's other frames)
    with torch.inference_mode():
        inputs[-1] = {k: v.clone() for k, v in inputs[-1].items()}
    ex = make_executor(model, backend, CPU, name, cache_dir=tmp_path, max_batch=b)
    assert ex.describe()["max_batch"] == b
    if backend == "compile":  # CUDA graphs are a CUDA-only feature; the CPU ignores the option
        assert ex.describe()["cudagraphs"] is False
    # compile: every batch size was compiled at warm-up, so none of these calls may compile again, though every
    # call gets new tensors (as mailbox slots do) of either kind; onnx: the export computes the exact
    # preprocessing, which the eager model then runs too
    exact = exact_preprocessing() if backend == "onnx" else contextlib.nullcontext()
    with torch.compiler.set_stance("fail_on_recompile"), exact:
        alone = [{k: v.clone() for k, v in ex(x).items()} for x in inputs]
        for n in range(b, 1, -1):
            together = {k: v.clone() for k, v in ex(cat(inputs[:n])).items()}
            check_outputs(name, model.output_spec, together, batch=n)
            assert_batch_is_its_frames(together, alone[:n], 1e-5, f"{name} on {backend}, a batch of {n}")
        assert_frames_differ(together, name)
        # ... and the batches are the eager model's
        eager = make_executor(build(cfg, name), "eager", CPU, name)
        want = eager(cat(inputs))
        assert_batch_is_its_frames(ex(cat(inputs)), [{k: v[i : i + 1] for k, v in want.items()} for i in range(b)],
                                   1e-4, f"{name} on {backend} vs eager")  # fmt: skip


@pytest.mark.parametrize("backend", [pytest.param("compile", marks=INDUCTOR), "onnx"])
def test_static_buffer_backends_refuse_batches_they_were_not_set_up_for(backend, tmp_path):
    cfg = tiny("thread")
    model = build(cfg, "depth")
    x = features_of(cfg, model, 2)
    ex = make_executor(model, backend, CPU, "depth", cache_dir=tmp_path, max_batch=1)
    with pytest.raises(BackendError, match=rf"depth: a batch of 2 frames; the {backend} backend was set up for 1 to 1"):
        ex(cat(x))
    two = {"patch.3": cat(x)["patch.3"]}
    ex2 = make_executor(build(cfg, "seg"), backend, CPU, "seg", cache_dir=tmp_path, max_batch=2)
    ex2(two)
    with pytest.raises(BackendError, match=r"max_batch must be a whole number >= 1, got 0"):
        make_executor(build(cfg, "depth"), backend, CPU, "depth", cache_dir=tmp_path, max_batch=0)


class _FixedBatch(Model):
    """A head whose code fixes its batch to a number (a loop over the frames): dynamo specialises each size."""

    role = "head"

    def __init__(self) -> None:
        super().__init__()
        self.input_spec = {"patch.3": TensorSpec((6, 4), "float32")}
        self.output_spec = {"y": TensorSpec((6, 4), "float32")}

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        x = inputs["patch.3"]
        return {"y": torch.stack([x[i] * (i + 1) for i in range(x.shape[0])])}


def compiled_graphs() -> int:
    return int(torch._dynamo.utils.counters["stats"]["unique_graphs"])


def test_a_model_that_fixes_its_batch_compiles_every_size_past_dynamo_s_recompile_limit():
    """Note [One compile for every batch]: the symbolic batch is a hint. A model whose code fixes its batch compiles
    once per size, as before, with no error; past torch._dynamo.config.recompile_limit (8) dynamo would quietly run
    the model eagerly, so here it must fail instead, and must not need to. (dynamo's own patch, not monkeypatch:
    after monkeypatch's undo, later compiles in the process found the entry missing)"""
    n = torch._dynamo.config.recompile_limit + 2
    torch._dynamo.reset()  # what earlier tests compiled must not count, nor be reused
    before = compiled_graphs()
    with torch._dynamo.config.patch(fail_on_recompile_limit_hit=True):
        ex = make_executor(_FixedBatch(), "compile", CPU, "h", max_batch=n, options={"compiler": "eager"})
        assert compiled_graphs() - before >= n  # a graph per size, at least
        x = torch.randn(n, 6, 4, generator=torch.Generator().manual_seed(0))
        with torch.compiler.set_stance("fail_on_recompile"):
            for b in (n, 1, n - 1):
                want = x[:b] * torch.arange(1, b + 1)[:, None, None]
                torch.testing.assert_close(ex({"patch.3": x[:b]})["y"], want)
    # its entries, past the limit, would count against the next compile of this head in the process (another test's)
    del ex
    torch._dynamo.reset()


@torch.library.custom_op("vpengine_test::fixed_batch_only", mutates_args=())
def _fixed_batch_only(x: torch.Tensor) -> torch.Tensor:
    return x * 2


@_fixed_batch_only.register_fake
def _(x: torch.Tensor) -> torch.Tensor:
    if isinstance(x.shape[0], torch.SymInt):  # as a kernel might whose shapes must be known when it is traced
        raise RuntimeError("fixed_batch_only: the batch must be a number")
    return torch.empty_like(x)


class _NoSymbolicBatch(_FixedBatch):
    """A head that compiles with every shape fixed and fails to with a symbolic batch."""

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {"y": _fixed_batch_only(inputs["patch.3"])}


def test_a_model_that_fails_to_compile_with_a_symbolic_batch_compiles_every_size_and_says_why(caplog):
    """Note [One compile for every batch]: a model the symbolic batch breaks still starts, compiled per size, with a
    warning naming it and the error; one that fails alone still fails, naming its error."""
    torch._dynamo.reset()
    before = compiled_graphs()
    with caplog.at_level(logging.WARNING, logger="vpengine.backends"):
        ex = make_executor(_NoSymbolicBatch(), "compile", CPU, "h", max_batch=4, options={"compiler": "aot_eager"})
    assert compiled_graphs() - before >= 4  # a graph per size: the symbolic one failed
    (warning,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert "h: compiling batches of 2 to 4 with one graph failed" in warning and "batch must be a number" in warning
    x = torch.randn(4, 6, 4, generator=torch.Generator().manual_seed(0))
    with torch.compiler.set_stance("fail_on_recompile"):
        for b in (4, 1, 3, 2):
            torch.testing.assert_close(ex({"patch.3": x[:b]})["y"], x[:b] * 2)
    caplog.clear()
    with pytest.raises(BackendError, match=r"h: torch.compile \(compiler 'aot_eager'\) failed at warm-up"):
        make_executor(_FailsAlone(), "compile", CPU, "h", max_batch=4, options={"compiler": "aot_eager"})
    assert not [r for r in caplog.records if "with one graph failed" in r.getMessage()]  # no batch to blame


class _FailsAlone(_FixedBatch):
    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        raise ValueError("a frame")


@pytest.mark.parametrize(
    ("head", "graphs"),
    [
        (None, 2),  # the foundation model: DINOv2 with registers
        ({"name": "h", "model": "dav2_depth_s", "options": DPT_WIDTHS}, 2),
        ({"name": "h", "model": "dinov2_linear_ade20k_s", "options": {"upsample": "torch"}}, 2),
        ({"name": "h", "model": "frcnn_dinov2_lite", "options": {"num_classes": 3, "score_threshold": 0.0}}, 3),
    ],
    ids=["dinov2", "dpt", "linear-seg", "faster-rcnn"],
)
def test_the_zoo_compiles_once_for_one_frame_and_once_for_every_batch(head, graphs):
    """Note [One compile for every batch]: the built-in models (small, of the released structure) compile a graph for
    a batch of one and one for batches of 2 to max_batch (the detector one more: its anchors fill a cache on the
    first call), not one per size; the batches are the eager model's, and none compiles again."""
    cfg = zoo_config(SMALL_DINOV2, [head] if head else [])
    name = "h" if head else "foundation"
    model = build(cfg, name)
    n = 5
    inputs = frames_of(cfg, n) if head is None else features_of(cfg, model, n)
    torch._dynamo.reset()  # what earlier tests compiled must not count, nor be reused
    before = compiled_graphs()
    ex = make_executor(model, "compile", CPU, name, max_batch=n, options={"compiler": "aot_eager"})
    assert compiled_graphs() - before == graphs
    eager = make_executor(build(cfg, name), "eager", CPU, name)
    with torch.compiler.set_stance("fail_on_recompile"):
        for b in (n, 3, 2, 1):
            got = {k: v.clone() for k, v in ex(cat(inputs[:b])).items()}
            want = eager(cat(inputs[:b]))
            assert_batch_is_its_frames(got, [{k: v[i : i + 1] for k, v in want.items()} for i in range(b)], 1e-4,
                                       f"{name}, a batch of {b}")  # fmt: skip


class _PatchAndClass(Model):
    """A head on patch tokens and a class token (as DPT's with ``use_clstoken`` reads them): inputs of two shapes."""

    role = "head"

    def __init__(self) -> None:
        super().__init__()
        self.input_spec = {"patch.0": TensorSpec((6, 4), "float32"), "cls.2": TensorSpec((4,), "float32")}
        self.output_spec = {"y": TensorSpec((6,), "float32")}

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {"y": (inputs["patch.0"] * inputs["cls.2"][:, None]).sum(-1)}


def test_inputs_of_one_call_must_hold_the_same_number_of_frames():
    # the check is the executor's, before the model runs: a head of two small inputs shows it as a zoo head would
    ex = make_executor(_PatchAndClass(), "compile", CPU, "h", max_batch=3, options={"compiler": "eager"})
    g = torch.Generator().manual_seed(0)
    x = {"patch.0": torch.randn(3, 6, 4, generator=g), "cls.2": torch.randn(3, 4, generator=g)}
    assert ex(x)["y"].shape == (3, 6)
    x["cls.2"] = x["cls.2"][:2]
    with pytest.raises(BackendError, match=r"h: input 'cls.2' holds 2 frames but 'patch.0' holds 3"):
        ex(x)


def test_a_worker_passes_its_slot_as_a_batch_of_one_and_copies_frame_zero_back():
    """The engine's workers read one frame per slot: what they hand the executor and copy back is exactly that
    frame's (thread mode, eager; the outputs equal the model's on the same frame)."""
    from vpengine.engine import Engine

    cfg = tiny("thread")
    img = frame(7)
    with Engine(cfg) as engine:
        fid = engine.submit(img)
        results = engine.wait(fid, timeout=30)
    depth = build(cfg, "depth")
    with torch.inference_mode():
        feats = build(cfg, "foundation")({"frame": torch.from_numpy(img)[None]})
        want = depth({k: feats[k] for k in depth.input_spec})["depth"][0].numpy()
    np.testing.assert_allclose(np.asarray(results["depth"]["depth"]), want, rtol=1e-5, atol=1e-6)
