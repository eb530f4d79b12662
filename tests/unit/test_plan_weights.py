"""What planning checks about weights, in the parent and before any worker: that each head reads the backbone and
the feature blocks its weights were trained on, and that every checkpoint is on disk (no processes, no downloads).
"""

from __future__ import annotations

import logging

import pytest
import torch

from vpengine.cli.main import main as cli
from vpengine.config import load_config
from vpengine.engine import Engine
from vpengine.models.base import ModelBuildError
from vpengine.models.build import build_model
from vpengine.models.weights import CheckpointError
from vpengine.runtime.plan import make_plan


@pytest.fixture
def empty_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("VPENGINE_CACHE", str(tmp_path / "cache"))
    for var in ("VPENGINE_CATALOG", "VPENGINE_OFFLINE", "HF_HUB_OFFLINE"):
        monkeypatch.delenv(var, raising=False)
    return tmp_path / "cache"


def dinov2(model: str, heads: list[dict], layers: list[int] | None = None, **weights: bool):
    options = {} if layers is None else {"layers": layers}
    return load_config(
        {
            "mode": "thread",
            "device": "cpu",
            "input": {"height": 56, "width": 56},
            "foundation_model": {"model": model, "options": options},
            "heads": heads,
            "weights": weights,
        }
    )


# ------------------------------------------------------------------------------- the backbone a head was trained on
def test_a_head_on_another_backbone_is_an_error_naming_both_sides_and_the_way_out():
    heads = [{"name": "x", "model": "helpers.models:TrainedElsewhere"}]
    with pytest.raises(ModelBuildError) as e:
        make_plan(load_config({"input": {"height": 56, "width": 56}, "heads": heads}))
    msg = str(e.value)
    assert "'x'" in msg and "'dinov2_vitl14'" in msg and "'dinov2_vits14'" in msg
    assert "accept_backbone_mismatch: true" in msg and "\n" not in msg


@pytest.mark.parametrize("ask", ["heads.x.accept_backbone_mismatch=true", "weights.random_weights=true"])
def test_an_explicit_ask_or_random_weights_turn_the_mismatch_into_a_warning(ask, caplog):
    cfg = load_config(
        {"input": {"height": 56, "width": 56}, "heads": [{"name": "x", "model": "helpers.models:TrainedElsewhere"}]},
        [ask],
    )
    with caplog.at_level(logging.WARNING, logger="vpengine.plan"):
        plan = make_plan(cfg)
    assert any("trained on backbone 'dinov2_vitl14'" in w and "degraded" in w for w in plan.warnings)
    assert "trained on backbone 'dinov2_vitl14'" in caplog.text


# ------------------------------------------------------------------------------- the blocks a head was trained on
def test_moving_the_block_a_head_reads_is_an_error_naming_both_blocks():
    seg = [{"name": "seg", "model": "dinov2_linear_ade20k_s"}]  # reads patch.3: block 11 of ViT-S
    with pytest.raises(ModelBuildError) as e:
        make_plan(dinov2("dinov2_vits14", seg, layers=[1, 3, 5, 7]))
    msg = str(e.value)
    assert "head 'seg'" in msg and "feature 3 from block 7 instead of block 11" in msg
    assert "[2, 5, 8, 11]" in msg and "[1, 3, 5, 7]" in msg and "accept_backbone_mismatch" in msg


def test_only_the_blocks_a_head_reads_count():
    seg = [{"name": "seg", "model": "dinov2_linear_ade20k_s"}]
    assert make_plan(dinov2("dinov2_vits14", seg)).warnings == []
    assert make_plan(dinov2("dinov2_vits14", seg, layers=[0, 1, 2, 11])).warnings == []  # patch.3 is still block 11
    depth = [{"name": "depth", "model": "dav2_depth_s"}]  # reads patch.0..3
    with pytest.raises(ModelBuildError, match=r"feature 0 from block 0 instead of block 2, feature 1 from block 1"):
        make_plan(dinov2("dinov2_vits14_dav2", depth, layers=[0, 1, 2, 11]))
    depth[0]["accept_backbone_mismatch"] = True
    plan = make_plan(dinov2("dinov2_vits14_dav2", depth, layers=[0, 1, 2, 11]))
    assert len(plan.warnings) == 1 and "instead of block 2" in plan.warnings[0]


# ------------------------------------------------------------------------------- checkpoints, before any worker
def flagship_heads() -> list[dict]:
    return [
        {"name": "depth", "model": "dav2_depth_s"},
        {"name": "seg", "model": "dinov2_linear_ade20k_s", "accept_backbone_mismatch": True},
        {"name": "det", "model": "frcnn_dinov2_lite", "checkpoint": "runs/det/head.pth", "options": {"num_classes": 3}},
    ]


def test_missing_checkpoints_fail_at_plan_time_one_line_each(empty_cache):
    cfg = dinov2("dinov2_vits14_dav2", flagship_heads())
    with pytest.raises(CheckpointError) as e:
        Engine(cfg)
    lines = str(e.value).splitlines()
    assert len(lines) == 4 and "no worker was started" in lines[0]
    shared = empty_cache / "weights" / "depth_anything_v2_vits" / "depth_anything_v2_vits.pth"
    assert lines[1].startswith("foundation, depth: ") and str(shared) in lines[1]
    assert "`vpengine weights fetch depth_anything_v2_vits`" in lines[1] and "huggingface.co" in lines[1]
    assert lines[2].startswith("seg: ") and "`vpengine weights fetch dinov2_vits14_ade20k_linear_head`" in lines[2]
    assert lines[3].startswith("det: ") and "runs/det/head.pth" in lines[3] and "does not exist" in lines[3]


def test_random_weights_need_no_checkpoint(empty_cache):
    cfg = load_config(dinov2("dinov2_vits14_dav2", flagship_heads()), ["weights.random_weights=true"])
    Engine(cfg)  # planned, never started: nothing to stop


def test_the_flagship_config_without_checkpoints_says_so_without_a_traceback(empty_cache, capsys):
    args = ["run", "-c", "dinov2s_depth_seg_det", "-s", "sample:cheetah", "--device", "cpu", "--mode", "thread"]
    assert cli(args) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.splitlines()) <= 5
    assert "foundation, depth: " in err and "seg: " in err and "det: " in err


def user_head(model: str, **head: object):
    return load_config(
        {
            "mode": "thread",
            "device": "cpu",
            "input": {"height": 56, "width": 56},
            "foundation_model": {"model": "tiny_vit"},
            "heads": [{"name": "mine", "model": f"helpers.models:{model}", **head}],
        }
    )


def test_a_user_head_that_loads_its_own_weights_is_never_refused(empty_cache):
    from helpers.models import OwnWeightsHead

    cfg = user_head("OwnWeightsHead")
    Engine(cfg)  # planned, no checkpoint asked for: nothing to refuse
    plan = make_plan(cfg)
    head = build_model(cfg, "mine", "head", plan.features, plan.feature_meta, torch.device("cpu"), plan_only=False)
    assert OwnWeightsHead.loaded[-1:] == ["mine"] and bool((head.proj.weight == 0.5).all())


def test_the_checkpoint_a_model_declares_is_the_one_checked_at_plan_time_and_loaded(empty_cache, tmp_path):
    cfg = user_head("DeclaredCheckpointHead")
    with pytest.raises(CheckpointError) as e:
        Engine(cfg)
    lines = str(e.value).splitlines()
    assert len(lines) == 2 and lines[1].startswith("mine: checkpoint 'my_site_depth' is neither an existing file")
    plan = make_plan(cfg)
    with pytest.raises(CheckpointError, match="^mine: checkpoint 'my_site_depth' is neither"):
        build_model(cfg, "mine", "head", plan.features, plan.feature_meta, torch.device("cpu"), plan_only=False)

    # A file in the config wins over the declared default, for the check and the load alike.
    meta = build_model(cfg, "mine", "head", plan.features, plan.feature_meta, torch.device("cpu"), plan_only=True)
    sd = {k: torch.full(v.shape, 0.25) for k, v in meta.state_dict().items()}
    torch.save(sd, tmp_path / "mine.pth")
    cfg = user_head("DeclaredCheckpointHead", checkpoint=str(tmp_path / "mine.pth"))
    Engine(cfg)
    head = build_model(cfg, "mine", "head", plan.features, plan.feature_meta, torch.device("cpu"), plan_only=False)
    assert bool((head.proj.weight == 0.25).all())


# ------------------------------------------------------------------------------- files that are not checkpoints
def test_a_file_that_is_not_a_checkpoint_is_refused_in_a_line_with_the_reason_and_the_fix(tmp_path):
    from vpengine.models.weights import read_state_dict

    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(bytes(range(256)) * 4)
    whole_model = tmp_path / "whole_model.pth"
    torch.save(torch.nn.Linear(2, 2), whole_model)  # the model pickled, not its state_dict
    for path, reason in ((garbage, "Unsupported operand"), (whole_model, "torch.nn.modules.linear.Linear")):
        with pytest.raises(CheckpointError) as e:
            read_state_dict(path)
        msg = str(e.value)
        assert "\n" not in msg and str(path) in msg and reason in msg, msg
        assert "save its state_dict" in msg
        assert "weights_only` set to `False`" not in msg and "file an issue" not in msg  # torch's advice: not ours


def test_a_folder_named_as_checkpoint_is_refused_naming_the_files_in_it(empty_cache, tmp_path, monkeypatch):
    (tmp_path / "head.pth").write_bytes(b"x")
    (tmp_path / "notes.txt").write_text("not a checkpoint")
    with pytest.raises(CheckpointError) as e:
        Engine(user_head("DeclaredCheckpointHead", checkpoint=str(tmp_path)))
    line = str(e.value).splitlines()[1]
    assert line == f"mine: checkpoint {str(tmp_path)!r} is a folder: name the checkpoint file in it; in it: head.pth"

    # a catalog name is the catalog's, whatever folder of that name is where the engine starts
    monkeypatch.chdir(tmp_path)
    (tmp_path / "depth_anything_v2_vits").mkdir()
    with pytest.raises(CheckpointError) as e:
        Engine(user_head("DeclaredCheckpointHead", checkpoint="depth_anything_v2_vits"))
    assert "`vpengine weights fetch depth_anything_v2_vits`" in str(e.value) and "is a folder" not in str(e.value)


def test_a_checkpoint_no_model_will_load_is_said_to_be_ignored(empty_cache, caplog, monkeypatch):
    from vpengine.models import weights

    cfg = user_head("TinyDepthHead", checkpoint="/data/runs/mine.pth")  # a head that declares no checkpoint
    with caplog.at_level(logging.WARNING, logger="vpengine.weights"):
        Engine(cfg)  # planned
    said = [r.getMessage() for r in caplog.records if "mine.pth" in r.getMessage()]
    assert said == [
        "mine: checkpoint '/data/runs/mine.pth' is set, but model 'helpers.models:TinyDepthHead' loads none (it "
        "declares none in needed_checkpoint and has no load_checkpoint of its own): it is ignored"
    ]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="vpengine.weights"):  # one that reads it itself is left alone
        Engine(user_head("OwnWeightsHead", checkpoint="/data/runs/mine.pth"))
    assert not [r for r in caplog.records if "mine.pth" in r.getMessage()]

    # random weights win over a configured checkpoint: the warning that says so names it
    monkeypatch.setattr(weights, "_RANDOM_WARNED", set())
    cfg = load_config(user_head("DeclaredCheckpointHead", checkpoint="site.pth"), ["weights.random_weights=true"])
    plan = make_plan(cfg)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="vpengine.weights"):
        build_model(cfg, "mine", "head", plan.features, plan.feature_meta, torch.device("cpu"), plan_only=False)
    assert any(
        "RANDOM WEIGHTS" in r.getMessage() and "its checkpoint 'site.pth' is not loaded" in r.getMessage()
        for r in caplog.records
    ), [r.getMessage() for r in caplog.records]


def test_a_worker_that_cannot_read_its_checkpoint_fails_the_start_in_a_line_without_a_traceback(empty_cache, tmp_path):
    from vpengine.engine import EngineStartError

    bad = tmp_path / "mine.pth"
    bad.write_bytes(b"\x80\x02not a checkpoint at all")
    eng = Engine(user_head("DeclaredCheckpointHead", checkpoint=str(bad)))
    with pytest.raises(EngineStartError) as e:
        eng.start()
    msg = str(e.value)
    assert f"CheckpointError: cannot read checkpoint {str(bad)!r}" in msg
    assert "Traceback" not in msg and msg.count("cannot read checkpoint") == 1, msg


def test_a_build_error_wrapping_another_keeps_the_traceback_of_its_cause():
    from vpengine.runtime.worker import describe_exception

    def user_code() -> None:
        raise KeyError("embed_dim")

    try:
        try:
            user_code()
        except KeyError as cause:
            raise ModelBuildError("mine: from_config failed") from cause
    except ModelBuildError as e:
        text = describe_exception("mine", e)
    assert text.splitlines()[0].endswith("ModelBuildError: mine: from_config failed")
    assert "Traceback" in text and "in user_code" in text  # where the user's bug is
    assert describe_exception("mine", ModelBuildError("mine: no such recipe")).count("\n") == 0


def test_a_missing_relative_checkpoint_says_it_was_taken_from_the_current_folder(tmp_path, monkeypatch):
    """The same config finds its file from one folder and not from another: a missing relative path says where it
    was looked for and why (the current folder, not the config's)."""
    from vpengine.models.weights import CheckpointError, locate_checkpoint

    monkeypatch.chdir(tmp_path)
    with pytest.raises(CheckpointError) as e:
        locate_checkpoint("det", "frcnn_dinov2_lite", "runs/det/head.pth")
    assert str(e.value) == (
        f"det: checkpoint file '{tmp_path / 'runs/det/head.pth'}' does not exist (and 'runs/det/head.pth' is not a "
        "catalog name; a relative path is taken from the current folder, not the config's)"
    )
    with pytest.raises(CheckpointError) as e:
        locate_checkpoint("det", "frcnn_dinov2_lite", str(tmp_path / "head.pth"))
    assert "current folder" not in str(e.value)
