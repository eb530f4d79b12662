"""Parameter accounting (`vpengine info --models`) against direct counts of real, CPU-built models."""

from __future__ import annotations

import json

import pytest
import torch

from tests_paths import TINY
from vpengine.cli.main import main as cli
from vpengine.config import load_config
from vpengine.models.accounting import parameter_report, sharing_saving
from vpengine.models.build import build_model
from vpengine.specs import TensorSpec


def direct_counts(cfg) -> dict[str, int]:
    """Build every model for real on the CPU (not the meta device the report uses) and count its parameters."""
    cpu = torch.device("cpu")
    frame = {"frame": TensorSpec((cfg.input.height, cfg.input.width, 3), cfg.input.dtype)}
    fm = build_model(cfg, "foundation", "foundation", frame, {}, cpu, plan_only=False)
    counts = {"foundation": sum(p.numel() for p in fm.parameters())}
    for h in cfg.heads:
        head = build_model(cfg, h.name, "head", fm.output_spec, fm.meta, cpu, plan_only=False)
        assert all(p.device.type == "cpu" for p in head.parameters())
        counts[h.name] = sum(p.numel() for p in head.parameters())
    counts["_tokens"], counts["_dim"] = fm.output_spec["patch.0"].shape[-2:]  # specs are per frame: [N, C]
    return counts


def test_report_matches_a_direct_count_of_every_model_of_the_tiny_config():
    cfg = load_config(TINY)
    report = parameter_report(cfg)
    direct = direct_counts(cfg)
    assert set(report["models"]) == {"foundation", "depth", "seg", "det"}
    for name, m in report["models"].items():
        assert m["params"] == direct[name], name
        assert m["param_bytes"] == 4 * m["params"]  # fp32
    assert report["models"]["depth"]["recipe"] == "tiny_depth"

    # And against the architecture itself: linear heads on C-dim tokens, K = 8 classes by default.
    c, k, n = direct["_dim"], 8, direct["_tokens"]
    assert report["models"]["depth"]["params"] == c + 1
    assert report["models"]["seg"]["params"] == c * k + k
    assert report["models"]["det"]["params"] == c * (1 + k) + 1 + k
    block = 2 * (2 * c) + (c * 3 * c + 3 * c) + (c * c + c) + (c * 2 * c + 2 * c) + (2 * c * c + c)
    vit = (3 * 14 * 14 * c + c) + c + (1 + n) * c + 4 * block + 2 * c
    assert report["models"]["foundation"]["params"] == vit


def test_the_sharing_saving_is_computed_from_the_counts():
    report = parameter_report(load_config(TINY))
    f = report["models"]["foundation"]["params"]
    heads = [report["models"][h]["params"] for h in ("depth", "seg", "det")]
    s = report["sharing"]
    assert s["heads"] == 3
    assert s["shared_total"] == f + sum(heads)
    assert s["independent_total"] == 3 * f + sum(heads)
    assert s["saved"] == 2 * f
    assert s["percent_fewer"] == pytest.approx(100 * 2 * f / (3 * f + sum(heads)))


@pytest.mark.parametrize(
    ("foundation", "heads", "shared", "independent", "percent"),
    [
        (100, [10, 10, 10], 130, 330, 100 * 200 / 330),
        (100, [5], 105, 105, 0.0),  # one head: nothing to share
        (100, [], 100, 100, 0.0),  # no heads: the backbone alone
    ],
)
def test_sharing_saving_edge_cases(foundation, heads, shared, independent, percent):
    s = sharing_saving(foundation, heads)
    assert (s["shared_total"], s["independent_total"]) == (shared, independent)
    assert s["saved"] == independent - shared
    assert s["percent_fewer"] == pytest.approx(percent)


def test_info_models_prints_the_report_as_json_and_text(capsys):
    assert cli(["info", "--models", "--config", str(TINY), "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown == json.loads(json.dumps(parameter_report(load_config(TINY))))

    assert cli(["info", "--models", "-c", str(TINY)]) == 0
    text = capsys.readouterr().out
    s = shown["sharing"]
    assert f"{s['shared_total']:,d}" in text and f"{s['independent_total']:,d}" in text
    assert f"{s['percent_fewer']:.1f}% fewer" in text
    for name, m in shown["models"].items():
        assert name in text and f"{m['params']:,d}" in text


def test_a_config_or_an_override_implies_models_rather_than_being_ignored(capsys):
    assert cli(["info", "-c", str(TINY), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == json.loads(json.dumps(parameter_report(load_config(TINY))))
    assert cli(["info", "--set", "bogus=1"]) == 1  # a typo is refused, not dropped
    assert "bogus" in capsys.readouterr().err


def test_info_models_applies_overrides(capsys):
    assert cli(["info", "--models", "-c", str(TINY), "--set", "foundation_model.options.embed_dim=64", "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["models"]["depth"]["params"] == 64 + 1  # the heads follow the wider backbone


def test_plain_info_output_is_unchanged(capsys):
    assert cli(["info", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert {"versions", "devices", "cuda", "mps", "kernels"} <= set(info)


def test_info_says_whether_the_fused_seg_kernel_runs_and_why_not(capsys):
    import torch

    assert cli(["info", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert "triton" in info["versions"]
    fused = info["kernels"]["fused_upsample_argmax"]
    if torch.cuda.is_available():
        assert fused == "available" or fused.startswith("not used: ")
    else:
        assert fused.startswith("not used: no CUDA device visible")
    assert cli(["info"]) == 0
    assert f"seg heads' fused upsample + argmax: {fused}" in capsys.readouterr().out


def test_info_models_without_a_config_accounts_for_the_shipped_gpu_config(capsys):
    # the built-in defaults have no head: a report of 0 heads saving 0 parameters says nothing
    assert cli(["info", "--models", "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert set(shown["models"]) == {"foundation", "depth", "seg", "det"} and shown["sharing"]["percent_fewer"] > 50
