"""The paper harness's configs: the engine is the config's, changed only by ``--set`` overrides, which reach the head
templates and every copy an experiment makes of them; the CLI has no flags of its own for engine settings; a missing
template, a bad experiment, head count or floor head, and E3 off CUDA are refused by name before anything starts."""

from __future__ import annotations

import argparse

import pytest

from tests_paths import ROOT
from vpengine.bench import paper
from vpengine.bench.paper import e3_mps, floor
from vpengine.bench.paper.harness import Bench
from vpengine.cli import bench as bench_cli

BENCH = str(ROOT / "configs" / "bench.yaml")
TINY = str(ROOT / "configs" / "tiny.yaml")


def test_overrides_reach_the_templates_and_every_copy_of_them():
    b = Bench.load(BENCH, ["mode=thread", "heads.depth.backend=eager", "heads.seg.options.upsample=torch"])
    cfg = b.config([b.head("depth", f"depth{i}") for i in range(3)] + [b.head("seg", "seg")])
    assert cfg.mode == "thread" and cfg.device == "cuda" and cfg.precision == "fp16"
    assert [h.name for h in cfg.heads] == ["depth0", "depth1", "depth2", "seg"]
    assert {h.backend for h in cfg.heads[:3]} == {"eager"}
    assert cfg.head("seg").backend == "compile" and cfg.head("seg").options == {"upsample": "torch"}
    assert cfg.foundation_model.backend == "compile"  # untouched: the config's
    # an experiment's own fields win over the config's for its engine alone (E1's independent models, the floor)
    assert b.config([b.head("depth", "d")], mode="process").mode == "process"
    assert b.head("depth", "r5", rate_hz=5)["rate_hz"] == 5 and b.base.head("depth").rate_hz is None


def test_the_results_file_records_what_ran():
    b = Bench.load(TINY, ["mode=thread"], frames=7, copy=False)
    s = b.setup()
    assert s["config"] == TINY and s["overrides"] == ["mode=thread"]
    assert (s["mode"], s["device"], s["backbone"], s["results"], s["frames"]) == (
        "thread",
        "cpu",
        "tiny_vit",
        "borrow",
        7,
    )
    assert s["heads"]["det"] == {"model": "tiny_det", "backend": "eager"}
    assert s["engine_config"]["heads"][0]["name"] == "depth"  # the whole config, as resolved


def test_a_missing_template_is_named_with_the_heads_the_config_has():
    b = Bench.load(TINY, [], frames=1)
    b.base = b.config([b.head("depth", "depth")])
    with pytest.raises(ValueError, match=r"needs a head named 'det'.* has \['depth'\]"):
        b.head("det", "det0")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    bench_cli.add_arguments(p)
    return p


@pytest.mark.parametrize(
    "flag",
    [
        "--sync-spin-us=200",
        "--wait-spin-us=0",
        "--feature-handoff=host",
        "--result-handoff=host",
        "--inline-launch=never",
        "--stream-priorities=depth=-1",
        "--no-slot-bound",
        "--seg-upsample=torch",
        "--backend=compile",
        "--mode=thread",
        "--mps=required",
        "--device=cpu",
        "--tiny",
    ],
)
def test_engine_settings_have_no_flags_of_their_own(flag, capsys):
    with pytest.raises(SystemExit):
        _parser().parse_args(["paper", flag])
    assert "unrecognized arguments" in capsys.readouterr().err


def test_set_is_the_way_in_as_in_vpengine_run():
    a = _parser().parse_args(["paper", "--set", "mode=thread", "--set", "heads.depth.backend=eager"])
    assert a.overrides == ["mode=thread", "heads.depth.backend=eager"]
    assert a.config == "bench"  # a shipped config, by name


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--experiments", "E1,E6"], "--experiments 'E1,E6': accepted are E1, E2, E3, E4, E5, floor"),
        (["--experiments", ""], "accepted are E1"),
        (["--heads", "2,x"], "--heads '2,x': expected head counts"),
        (["--heads", "0"], "at least 1"),
        (["--floor-heads", "depth,sky"], r"floor heads \['depth', 'sky'\]: accepted are depth, seg, det"),
        (["--floor-batches", "1,four"], "--floor-batches '1,four': expected frame counts like"),
        (["--floor-batches", "4,0"], "--floor-batches '4,0': expected frame counts of at least 1"),
        (["--experiments", "E1,E3"], "E3 compares CUDA MPS off and on: it needs device cuda"),
        (["--experiments", "E1,E2", "--set", "heads.det.name=boxes"], "needs a head named 'det'"),
    ],
)
def test_bad_arguments_are_refused_by_name_before_any_engine_starts(args, named, tmp_path):
    a = _parser().parse_args(["paper", "--config", TINY, "--out", str(tmp_path), *args])
    with pytest.raises(ValueError, match=named):
        paper.main(a)
    assert not list(tmp_path.iterdir())


def test_e3_needs_cuda():
    with pytest.raises(ValueError, match="E3 compares CUDA MPS off and on: it needs device cuda.*'cpu'"):
        e3_mps.run(Bench.load(TINY), [])


def test_floor_heads_are_the_template_kinds():
    assert floor.check_kinds(("depth", "seg")) == ("depth", "seg")
    with pytest.raises(ValueError, match="at least one"):
        floor.check_kinds(())
