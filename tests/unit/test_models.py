"""Model interface, preprocessing and build-time pipeline checks (no processes)."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

from tests_paths import tiny
from vpengine.config import PreprocessConfig, load_config
from vpengine.models.base import ModelBuildError, Pipeline, check_outputs
from vpengine.models.build import build_model
from vpengine.models.preprocess import IMAGENET_MEAN, IMAGENET_STD, ImagePreprocess, target_size
from vpengine.runtime.plan import make_plan
from vpengine.specs import TensorSpec


@pytest.mark.parametrize(
    ("hw", "cfg", "expected"),
    [
        ((1080, 1920), {}, (518, 924)),  # the documented 1080p case: 37 x 66 tokens
        ((1080, 1920), {"resize": "square"}, (518, 518)),
        ((480, 640), {}, (518, 686)),
        ((576, 768), {}, (518, 686)),
        ((1920, 1080), {}, (924, 518)),  # portrait
        ((100, 100), {"resize": "none"}, (98, 98)),
    ],
)
def test_target_size_preserves_aspect_and_patch_multiple(hw, cfg, expected):
    size = target_size(*hw, PreprocessConfig(**cfg), 14)
    assert size == expected and size[0] % 14 == 0 and size[1] % 14 == 0


def test_preprocess_matches_a_hand_computation():
    frame = np.random.default_rng(0).integers(0, 256, (28, 42, 3), dtype=np.uint8)
    cfg = PreprocessConfig(resize="none")
    pre = ImagePreprocess(28, 42, cfg, 14, color="bgr")
    out = pre({"frame": torch.from_numpy(frame)[None]})["image"]  # a batch of one frame
    rgb = frame[..., ::-1].astype(np.float32) / 255
    ref = (rgb - np.array(IMAGENET_MEAN)) / np.array(IMAGENET_STD)
    assert out.shape == (1, 3, 28, 42)
    np.testing.assert_allclose(out[0].permute(1, 2, 0).numpy(), ref, rtol=1e-5, atol=1e-5)
    rgb_pre = ImagePreprocess(28, 42, cfg, 14, color="rgb")
    out_rgb = rgb_pre({"frame": torch.from_numpy(np.ascontiguousarray(frame[..., ::-1]))[None]})["image"]
    torch.testing.assert_close(out, out_rgb)


def test_plan_builds_on_meta_device_and_declares_specs():
    plan = make_plan(tiny())
    assert plan.frame_spec == {"frame": TensorSpec((120, 160, 3), "uint8")}
    assert set(plan.features) == {f"{k}.{i}" for k in ("patch", "cls") for i in range(4)}
    assert all(p.device.type == "meta" for p in plan.foundation.parameters())
    assert plan.heads["depth"].output_spec == {"depth": TensorSpec((120, 160), "float32")}
    assert plan.heads["det"].output_spec["count"] == TensorSpec((), "int32")
    # one frame per spec, no batch dimension anywhere (Note [Batched models])
    assert plan.features["patch.3"] == TensorSpec((88, 32), "float32")
    assert plan.features["cls.3"] == TensorSpec((32,), "float32")
    assert plan.foundation.stages[0].output_spec == {"image": TensorSpec((3, 112, 154), "float32")}
    assert plan.feature_meta["grid"] == (8, 11)  # 120x160 -> 112x154 -> 8x11 tokens


def test_real_build_runs_and_matches_declared_specs():
    cfg = tiny()
    plan = make_plan(cfg)
    fm = build_model(cfg, "foundation", "foundation", plan.frame_spec, {}, torch.device("cpu"), False)
    feats = fm(fm.example_inputs())
    check_outputs("foundation", plan.features, feats, batch=1)
    for k, spec in plan.features.items():
        assert feats[k].shape[0] == 1 and spec.matches(feats[k][0])  # specs have no batch dimension
    for name, meta_model in plan.heads.items():
        head = build_model(cfg, name, "head", plan.features, plan.feature_meta, torch.device("cpu"), False)
        out = head({k: feats[k] for k in head.input_spec})
        check_outputs(name, meta_model.output_spec, out, batch=1)
        for k, spec in meta_model.output_spec.items():
            assert out[k].shape[0] == 1 and spec.matches(out[k][0]), (name, k)


def test_check_outputs_wants_one_leading_batch_dimension_on_every_output():
    spec = {"depth": TensorSpec((4, 5), "float32"), "count": TensorSpec((), "int32")}
    good = {"depth": torch.zeros(3, 4, 5), "count": torch.zeros(3, dtype=torch.int32)}
    check_outputs("h", spec, good)
    check_outputs("h", spec, good, batch=3)
    with pytest.raises(
        ModelBuildError,
        match=r"h: outputs differ .*depth: declared float32\[4, 5\] per frame, so float32\[2, 4, 5\] for a "
        r"batch of 2; got torch.float32\[3, 4, 5\].*count: declared int32\[\] per frame, so int32\[2\]",
    ):
        check_outputs("h", spec, good, batch=2)
    with pytest.raises(ModelBuildError, match=r"output_spec: depth: declared") as e:  # nothing missing, not said
        check_outputs("h", spec, {**good, "depth": torch.zeros(3, 4, 5)}, batch=2)
    assert "missing" not in str(e.value)
    with pytest.raises(ModelBuildError, match=r"depth: .*got torch.float32\[4, 5\]"):  # one frame, unbatched
        check_outputs("h", spec, {"depth": torch.zeros(4, 5), "count": torch.zeros(4, dtype=torch.int32)})
    with pytest.raises(ModelBuildError, match=r"count: .*for a batch of 3; got torch.int32\[2\]"):
        check_outputs("h", spec, {**good, "count": torch.zeros(2, dtype=torch.int32)})
    with pytest.raises(ModelBuildError, match=r"missing \['count'\]"):
        check_outputs("h", spec, {"depth": good["depth"]})


def test_check_outputs_names_the_batch_size_it_assumed_and_never_takes_a_frame_dimension_for_one():
    spec = {"seg": TensorSpec((6, 8), "uint8")}
    unbatched = {"seg": torch.zeros(6, 8, dtype=torch.uint8)}  # one frame's map, its batch dimension forgotten
    with pytest.raises(
        ModelBuildError,
        match=r"so uint8\[B, 6, 8\] for a batch of B; got torch.uint8\[6, 8\].*\(B: none was given, and no output has",
    ):
        check_outputs("seg", spec, unbatched)  # not "a batch of 6": 6 is the map's height
    with pytest.raises(
        ModelBuildError,
        match=r"so uint8\[1, 6, 8\] for a batch of 1; .*\(a batch of 1: the frames the model was given\)",
    ):
        check_outputs("seg", spec, unbatched, batch=1)
    with_count = {**spec, "count": TensorSpec((), "int32")}
    with pytest.raises(
        ModelBuildError,
        match=r"so uint8\[2, 6, 8\] for a batch of 2; .*\(a batch of 2: read off the leading dimension of 'count'",
    ):
        check_outputs("seg", with_count, {**unbatched, "count": torch.zeros(2, dtype=torch.int32)})


def test_example_inputs_are_a_batch_of_the_specs():
    fm = make_plan(tiny()).foundation
    one, three = fm.example_inputs(batch=1), fm.example_inputs(batch=3)
    assert one["frame"].shape == (1, 120, 160, 3) and three["frame"].shape == (3, 120, 160, 3)
    assert one["frame"].dtype == torch.uint8 and one["frame"].device.type == "cpu"
    assert not torch.equal(three["frame"][0], three["frame"][1])  # different frames, never zeros
    with pytest.raises(ValueError, match="batch must be at least 1, got 0"):
        fm.example_inputs(batch=0)


def test_same_recipe_gives_same_weights_in_every_build():
    cfg = tiny()
    plan = make_plan(cfg)
    a = build_model(cfg, "foundation", "foundation", plan.frame_spec, {}, torch.device("cpu"), False)
    b = build_model(cfg, "foundation", "foundation", plan.frame_spec, {}, torch.device("cpu"), False)
    for (ka, va), (kb, vb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert ka == kb and torch.equal(va, vb)


def test_unknown_model_names_the_known_ones():
    # the field that names it, as a config error names its field
    with pytest.raises(
        ModelBuildError, match=r"^heads.depth.model: unknown head model 'tiny_dpth'; known: .*tiny_depth"
    ):
        make_plan(tiny("process", "heads.depth.model=tiny_dpth"))
    with pytest.raises(ModelBuildError, match="^foundation_model.model: model 'tiny_depth' is a head model and cannot"):
        make_plan(tiny("process", "foundation_model.model=tiny_depth"))
    with pytest.raises(ModelBuildError, match="cannot be imported"):
        make_plan(tiny("process", "heads.depth.model=nowhere.mod:Thing"))


def test_head_needing_a_feature_the_backbone_lacks_fails_with_names():
    cfg = load_config(
        {
            "input": {"height": 56, "width": 56},
            "foundation_model": {"model": "tiny_vit"},
            "heads": [{"name": "x", "model": "helpers.models:NeedsMissingFeature"}],
        }
    )
    with pytest.raises(ModelBuildError) as e:
        make_plan(cfg)
    assert "'x'" in str(e.value) and "'patch.9'" in str(e.value) and "tiny_vit" in str(e.value)


def test_bad_recipe_options_name_the_accepted_ones():
    # the dotted field, as a config error names one
    with pytest.raises(
        ModelBuildError,
        match=r"^bad options for 'tiny_depth': heads.depth.options.colour: unknown key \(accepted: .*num_classes",
    ):
        make_plan(tiny("process", "heads.depth.options={colour: red}"))


def test_pipeline_rejects_mismatched_links():
    pre = ImagePreprocess(28, 28, PreprocessConfig(resize="none"), 14)
    other = ImagePreprocess(56, 56, PreprocessConfig(resize="none"), 14)
    with pytest.raises(
        ModelBuildError, match=r"needs 'frame' as uint8\[56, 56, 3\] but it is produced as uint8\[28, 28, 3\]"
    ):
        Pipeline(pre, other)


def test_models_built_in_parallel_threads_get_the_same_seeded_weights():
    """Thread mode builds every model at once; construction uses PyTorch's global RNG, so builds must not mix."""
    import threading

    cfg = load_config(
        {
            "input": {"height": 56, "width": 84},
            "weights": {"random_weights": True},
            "foundation_model": {
                "model": "dinov2_vits14",
                "options": {"size": "custom", "embed_dim": 32, "depth": 4, "heads": 2},
            },
            "heads": [{"name": f"h{i}", "model": "tiny_depth"} for i in range(3)],
        }
    )
    plan = make_plan(cfg)
    cpu = torch.device("cpu")
    reference = build_model(cfg, "foundation", "foundation", plan.frame_spec, {}, cpu, False).state_dict()
    for _ in range(3):
        built = {}

        def fm(built=built):
            built["fm"] = build_model(cfg, "foundation", "foundation", plan.frame_spec, {}, cpu, False)

        def head(n):
            for _ in range(20):  # default layer init draws from the global RNG meanwhile
                build_model(cfg, n, "head", plan.features, plan.feature_meta, cpu, False)

        threads = [threading.Thread(target=fm)] + [threading.Thread(target=head, args=(f"h{i}",)) for i in range(3)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for k, v in built["fm"].state_dict().items():
            assert torch.equal(v, reference[k]), k


def test_cpu_uint8_fast_resize_stays_within_one_grey_level_of_the_float_path():
    frame = torch.from_numpy(np.random.default_rng(3).integers(0, 256, (270, 480, 3), dtype=np.uint8))
    cfg = PreprocessConfig(size=112)
    pre = ImagePreprocess(270, 480, cfg, 14)
    fast = pre({"frame": frame[None]})["image"]  # uint8 on the CPU: resized before the float conversion
    pre_f = ImagePreprocess(270, 480, cfg, 14, in_dtype="float32")  # float frames take the float path
    slow = pre_f({"frame": frame[None].float() / 255})["image"]
    assert fast.shape == slow.shape == (1, 3, 112, 196)
    one_level = (1 / 255) / min(IMAGENET_STD)  # one grey level in normalised units
    assert (fast - slow).abs().max().item() <= one_level
    assert (fast - slow).abs().mean().item() < 0.5 * one_level


def test_planning_the_tiny_pipeline_imports_no_compiler():
    """Every CLI start plans its config on the meta device. Integer arithmetic there runs PyTorch's Python reference
    kernels, whose first use imports torch._dynamo (~2 s on a small machine), which the README's tiny job never
    needs: its detection head computes its cell boxes on the CPU."""
    import subprocess
    import sys

    code = (
        "import sys, torch\n"
        "from vpengine.config import load_config\n"
        "from vpengine.runtime.plan import make_plan\n"
        "plan = make_plan(load_config('configs/tiny.yaml'))\n"
        "assert set(plan.heads) == {'depth', 'seg', 'det'}, plan.heads\n"
        "print('torch._dynamo' in sys.modules)\n"
    )
    from tests_paths import ROOT

    p = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.split() == ["False"], p.stdout


def test_the_tiny_detection_heads_cells_are_built_where_the_model_is():
    cfg = tiny("thread")
    plan = make_plan(cfg)
    for device in ("meta", "cpu"):
        head = build_model(cfg, "det", "head", plan.features, plan.feature_meta, torch.device(device), device == "meta")
        assert head.cells.device.type == device and head.cells.shape[-1] == 4
    gh, gw = plan.feature_meta["grid"]
    h, w = cfg.input.height, cfg.input.width
    want = torch.tensor([[0, 0, w / gw, h / gh], [w - w / gw, h - h / gh, w, h]])
    assert torch.allclose(head.cells[[0, -1]], want)


# ------------------------------------------------------------------------------- a user model that is not found
def test_a_user_model_not_found_says_where_python_looked_and_the_fix(tmp_path, monkeypatch):
    from vpengine.models import registry

    here = str(tmp_path)
    monkeypatch.chdir(tmp_path)
    # as the vpengine command runs: the current folder is not on the import path
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", ".", here)])
    (tmp_path / "my_site_pkg").mkdir()
    (tmp_path / "my_site_pkg" / "__init__.py").write_text("")
    (tmp_path / "my_site_pkg" / "heads.py").write_text("import surely_not_installed_dep\n")

    with pytest.raises(ModelBuildError) as e:
        registry.resolve("my_site_pkg.heads:MyHead", "head")
    assert str(e.value) == (
        "model 'my_site_pkg.heads:MyHead' cannot be imported: No module named 'my_site_pkg'; 'my_site_pkg' is in the "
        f"current folder {here!r}, where the vpengine command does not look: run with PYTHONPATH=. or install its "
        "package (pip install -e) (docs/models.md, Your own head)"
    )
    with pytest.raises(ModelBuildError, match="; put the folder that holds it on PYTHONPATH, or install its package"):
        registry.resolve("elsewhere_pkg.heads:MyHead", "head")

    monkeypatch.syspath_prepend(here)  # found now: what it imports is not
    with pytest.raises(ModelBuildError) as e:
        registry.resolve("my_site_pkg.heads:MyHead", "head")
    assert str(e.value).endswith(
        "No module named 'surely_not_installed_dep' (a module 'my_site_pkg.heads' imports: install it in this "
        "environment)"
    )

    with pytest.raises(ModelBuildError) as e:  # the package is there, its module is not: a typo
        registry.resolve("my_site_pkg.headz:MyHead", "head")
    assert str(e.value).endswith(
        f"No module named 'my_site_pkg.headz'; package 'my_site_pkg' (found at {tmp_path / 'my_site_pkg'!s}) has "
        "no module 'headz'"
    )
    (tmp_path / "my_site_pkg" / "broken.py").write_text("def oops(:\n")
    with pytest.raises(ModelBuildError) as e:  # its own code fails: said, with the error chained for its traceback
        registry.resolve("my_site_pkg.broken:MyHead", "head")
    assert "importing 'my_site_pkg.broken' failed: SyntaxError" in str(e.value)
    assert isinstance(e.value.__cause__, SyntaxError)
    with pytest.raises(ModelBuildError, match="a relative module; name it from its package"):
        registry.resolve(".heads:MyHead", "head")


def test_a_user_heads_own_error_at_build_names_the_head_and_keeps_its_traceback():
    with pytest.raises(ModelBuildError) as e:
        make_plan(tiny("thread", "heads.depth.model=helpers.models:RaisingHead"))
    assert str(e.value) == "heads.depth (helpers.models:RaisingHead): building it raised KeyError: 'patch.7'"
    assert isinstance(e.value.__cause__, KeyError)  # the traceback of where it raised is kept
    with pytest.raises(ModelBuildError, match=r"^heads.depth \(helpers.models:NoSuperInitHead\): .*super\(\).__init__"):
        make_plan(tiny("thread", "heads.depth.model=helpers.models:NoSuperInitHead"))
    with pytest.raises(ModelBuildError, match=r"from_config returned a NoneType, not the model built"):
        make_plan(tiny("thread", "heads.depth.model=helpers.models:ReturnsNothingHead"))
