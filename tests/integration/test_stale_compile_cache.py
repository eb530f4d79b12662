"""A compile cache that another release left on disk neither breaks nor changes a compile start (issue 28: such a
cache failed the E5 start with "seg: outputs differ from the declared output_spec"). Note [Compile cache key]."""

from __future__ import annotations

import getpass
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from helpers.compile_start import Affine, example
from tests_paths import ROOT
from vpengine.backends.compile_cache import compile_key
from vpengine.runtime.process import package_env


def start(tmp_path: Path, **env: str) -> dict:
    """One compile start in a process of its own (inductor keeps per-process state), with ``<tmp>/cache`` as the
    vpengine cache and ``<tmp>/tmp`` as the temporary folder (where inductor's default cache lies)."""
    run_env = package_env()
    for var in ("TORCHINDUCTOR_CACHE_DIR", "TRITON_CACHE_DIR"):
        run_env.pop(var, None)
    run_env.update(VPENGINE_CACHE=str(tmp_path / "cache"), TMPDIR=str(tmp_path / "tmp"), **env)
    run_env["PYTHONPATH"] += f":{ROOT / 'tests'}"
    done = subprocess.run(
        [sys.executable, "-m", "helpers.compile_start"], env=run_env, capture_output=True, text=True, timeout=500
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def entries(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_a_stale_compile_cache_of_another_release_neither_breaks_nor_changes_a_start(tmp_path):
    (tmp_path / "tmp").mkdir()
    # inductor's own default, where a release without keyed caches left what it compiled: <TMPDIR>/torchinductor_<user>
    old = tmp_path / "tmp" / f"torchinductor_{re.sub(r'[^A-Za-z0-9_.-]', '_', getpass.getuser())}"
    # That release compiled the same model there (here: into a folder the user names, which is used as it is, then
    # copied there; inductor keeps its precompiled headers there whatever the cache, keyed on their flags) ...
    before = start(tmp_path, TORCHINDUCTOR_CACHE_DIR=str(tmp_path / "mine"))
    assert before["compile_cache"] == str(tmp_path / "mine")
    left = entries(tmp_path / "mine")
    # the folders that an FX graph's and an AOTAutograd entry's keys name: where a start looks them up
    keys = {k.rsplit("/", 1)[0] for k in left if k.startswith(("fxgraph/", "aotautograd/"))}
    assert keys, sorted(left)
    # ... and left entries that are garbage now (a graph of another release would be as wrong, and no louder); so
    # did a release with a folder of its own.
    other = tmp_path / "cache" / "compile" / "vpengine-0.0.1-torch-2.0.0-py310-0123456789abcdef" / "inductor"
    for folder in (old, other):
        for name in left:
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_bytes(b"written by another release\n")
    stale = {folder: {k: v for k, v in entries(folder).items() if k in left} for folder in (old, other)}

    after = start(tmp_path)

    assert after["y"] == before["y"]  # the same outputs as the start before the cache went stale
    with torch.inference_mode():
        assert torch.allclose(torch.tensor(after["y"]), Affine().eval()(example())["y"], atol=1e-6)
    ours = Path(after["compile_cache"])
    assert ours == tmp_path / "cache" / "compile" / compile_key() / "inductor"
    # the start looked up and compiled into its own folder the very keys it would have found stale in the old one ...
    assert keys <= {k.rsplit("/", 1)[0] for k in entries(ours)}
    # ... and read nothing it found there: what another release left is still there, untouched, and not in use
    assert {folder: {k: v for k, v in entries(folder).items() if k in left} for folder in (old, other)} == stale
