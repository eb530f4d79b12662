"""Where ``vpengine bench`` writes: ``--out``, by default a new folder named for the run in the current folder,
never a clone's tracked ``benchmarks/results``."""

from __future__ import annotations

import importlib

import pytest

from tests_paths import ROOT
from vpengine.cli import bench
from vpengine.cli.main import build_parser

REQUIRED = {"report": ["--results", "."]}  # what a subcommand cannot run without


@pytest.mark.parametrize("name", list(bench.BENCHES))
def test_every_bench_writes_by_default_into_a_new_folder_named_for_it_here(tmp_path, monkeypatch, name):
    clone = tmp_path / "clone"
    (clone / "benchmarks" / "results").mkdir(parents=True)  # run from a clone's root, as the docs do
    monkeypatch.chdir(clone)
    seen = []
    monkeypatch.setattr(importlib.import_module(bench.BENCHES[name][0]), "main", lambda args: seen.append(args.out))
    args = build_parser().parse_args(["bench", name, *REQUIRED.get(name, [])])
    assert bench.main(args) == 0
    (out,) = seen
    path = (clone / out).resolve()
    assert path.is_dir() and path.parent == clone and path.name.startswith(f"bench-{name}-"), out
    assert not path.is_relative_to(clone / "benchmarks") and not path.is_relative_to(ROOT / "benchmarks")
    assert list((clone / "benchmarks" / "results").iterdir()) == []
    again = build_parser().parse_args(["bench", name, *REQUIRED.get(name, [])])
    bench.main(again)  # a second run in the same second gets a folder of its own
    assert seen[1] != seen[0] and (clone / seen[1]).is_dir()


def test_out_is_made_when_missing_and_refused_when_a_file(tmp_path):
    assert bench.out_folder("hop", str(tmp_path / "a" / "b")) == tmp_path / "a" / "b"
    assert (tmp_path / "a" / "b").is_dir()
    assert bench.out_folder("hop", str(tmp_path / "a")) == tmp_path / "a"  # an existing folder: written into
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match="--out .*is a file"):
        bench.out_folder("hop", str(tmp_path / "f"))
