"""Note [Compile cache key]: the compile caches' folder is named by everything that shapes what is compiled, and
only a folder the user chose is left alone."""

from __future__ import annotations

import os
import platform
import re

import pytest
import torch

from vpengine.backends import compile_cache
from vpengine.backends.compile_cache import CACHE_VARIABLES, compile_key, use_compile_cache


@pytest.fixture
def fresh(monkeypatch):  # type: ignore[no-untyped-def]
    """A process that has set no compile cache yet, and whose variables come back as they were after the test."""
    for var in CACHE_VARIABLES:
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(compile_cache, "_ours", {})
    compile_key.cache_clear()
    yield monkeypatch
    compile_key.cache_clear()


def test_the_key_names_the_releases_and_changes_with_every_part(fresh):
    key = compile_key()
    assert re.fullmatch(r"[A-Za-z0-9._-]+", key), key  # one folder name on any file system
    assert key.startswith(
        f"vpengine-{compile_cache.__version__}-torch-{re.sub(r'[^A-Za-z0-9._-]', '_', torch.__version__)}"
    )
    assert compile_key() == key  # the same install, the same folder
    changes = {
        "vpengine release": (compile_cache, "__version__", "0.0.1"),
        "vpengine source": (compile_cache, "_source_digest", lambda: "an edit that kept the version"),
        "torch release": (torch, "__version__", "2.0.0"),
        "torch build": (torch.version, "git_version", "0" * 40),
        "triton release": (compile_cache, "_triton_version", lambda: "2.0.0"),
        "machine": (platform, "machine", lambda: "riscv64"),
    }
    seen = {key}
    for what, (owner, attr, value) in changes.items():
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(owner, attr, value)
            compile_key.cache_clear()
            other = compile_key()
        assert other not in seen, what
        seen.add(other)
    compile_key.cache_clear()
    assert compile_key() == key


def test_caches_go_to_the_keyed_folder_unless_the_user_chose_one(fresh, tmp_path):
    folders = use_compile_cache(tmp_path / "a")
    want = {var: str(tmp_path / "a" / compile_key() / sub) for var, sub in CACHE_VARIABLES.items()}
    assert folders == want and {var: os.environ[var] for var in CACHE_VARIABLES} == want
    # a folder this process chose before (another cache root) is replaced
    assert use_compile_cache(tmp_path / "b")["TORCHINDUCTOR_CACHE_DIR"] == str(
        tmp_path / "b" / compile_key() / "inductor"
    )
    # the user's folder is the user's: kept, whatever its name
    fresh.setenv("TRITON_CACHE_DIR", str(tmp_path / "mine"))
    folders = use_compile_cache(tmp_path / "c")
    assert folders["TRITON_CACHE_DIR"] == str(tmp_path / "mine")
    assert folders["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / "c" / compile_key() / "inductor")


def test_inductors_default_written_back_to_the_environment_is_not_taken_for_the_users(fresh, tmp_path):
    default = compile_cache._inductor_default()
    assert default is not None
    fresh.setenv("TORCHINDUCTOR_CACHE_DIR", default)  # what inductor's cache_dir() leaves after its first look
    assert use_compile_cache(tmp_path)["TORCHINDUCTOR_CACHE_DIR"] == str(tmp_path / compile_key() / "inductor")
