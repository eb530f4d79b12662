"""A fetch without a network: offline mode, or servers that cannot be reached (a closed port on 127.0.0.1 stands in
for no network). Each file gets one line, naming why, the path to place it at and the URL to get it from; no
retries, no retry log, exit 1."""

from __future__ import annotations

import hashlib
import socket

import pytest

from vpengine.cli.main import main as cli
from vpengine.models import catalog, download
from vpengine.models.catalog import Catalog, Entry
from vpengine.models.weights import CheckpointError

pytestmark = pytest.mark.timeout(120)

DIGEST = hashlib.sha256(b"x").hexdigest()


@pytest.fixture
def dead() -> str:
    """A base URL nothing listens on."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"http://127.0.0.1:{port}"


@pytest.fixture
def env(tmp_path, monkeypatch):
    monkeypatch.setenv("VPENGINE_CACHE", str(tmp_path / "cache"))
    for var in ("VPENGINE_OFFLINE", "HF_HUB_OFFLINE", "VPENGINE_CATALOG", "HF_ENDPOINT"):
        monkeypatch.delenv(var, raising=False)
    return tmp_path / "cache"


def entries(dead: str) -> list[Entry]:
    common = {"licence": "Apache-2.0", "recipes": ("tiny_vit",), "source": "the test"}
    return [
        Entry(name="plain_a", url=f"{dead}/a.pth", file="a.pth", sha256=DIGEST, size=1, **common),
        Entry(
            name="plain_b", url=f"{dead}/b.pth", file="b.pth", sha256=None, size=None, sha256_missing="none", **common
        ),
        Entry(
            name="hub_c",
            url="https://huggingface.co/org/repo/resolve/main/c.pth",
            file="c.pth",
            sha256=DIGEST,
            size=1,
            **common,
        ),
    ]


def assert_one_line_each(err: str, cat: list[Entry], cache, why: str, hub: str = "https://huggingface.co") -> None:
    """``hub``: the Hub endpoint in force, whose URL the line names for a Hub file."""
    lines = err.strip().splitlines()
    assert len(lines) == len(cat), err
    for line, e in zip(lines, cat):
        assert line.startswith(f"vpengine weights fetch: {e.name}: ") and why in line
        url = e.url.replace("https://huggingface.co", hub)
        assert f"place the file at {e.path(cache)} (download it from {url};" in line
    assert "Retrying" not in err and "Traceback" not in err and "WARNING" not in err


def test_unreachable_servers_give_one_line_per_file_without_retries(dead, env, monkeypatch, capsys):
    monkeypatch.setenv("HF_ENDPOINT", dead)  # the Hub is unreachable too
    cat = entries(dead)
    with catalog.use(Catalog(cat)):
        assert cli(["weights", "fetch", *(e.name for e in cat)]) == 1
    err = capsys.readouterr().err
    assert_one_line_each(err, cat, env, f"{dead.removeprefix('http://')} is unreachable (", hub=dead)
    assert not list(env.rglob("*.pth*"))  # nothing half-written


def test_an_unreachable_url_entry_is_told_the_command_that_fetches_it_again(dead, env, capsys):
    # a --url entry is recorded only once fetched: the command to run next names its URL, and the digest given
    url, digest = f"{dead}/mine.pth", "ab" * 32
    with catalog.use(Catalog()):
        assert cli(["weights", "fetch", "mine", "--url", url, "--sha256", digest]) == 1
        err = capsys.readouterr().err
        assert f"sha256 {digest} as you gave it: `vpengine weights fetch mine --url {url} --sha256 {digest}`" in err
        assert cli(["weights", "fetch", "mine", "--url", url, "--trust-on-first-use"]) == 1
        err = capsys.readouterr().err
        assert f"`vpengine weights fetch mine --url {url} --trust-on-first-use` then records the digest" in err


def test_offline_gives_one_line_per_file_and_makes_no_request(dead, env, capsys):
    cat = entries(dead)
    with catalog.use(Catalog(cat)):
        assert cli(["weights", "fetch", "--offline", *(e.name for e in cat)]) == 1
    assert_one_line_each(capsys.readouterr().err, cat, env, "offline mode, not downloaded")


def test_fetch_raises_unreachable_naming_the_host_and_the_place_for_the_file(dead, env):
    cat = entries(dead)
    with catalog.use(Catalog(cat)), pytest.raises(download.Unreachable) as e:
        download.fetch(cat[0], env, progress=False)
    assert e.value.host == dead.removeprefix("http://") and str(cat[0].path(env)) in str(e.value)
    assert isinstance(e.value, CheckpointError)


def test_a_login_in_a_url_or_the_hub_endpoint_never_shows_in_messages(dead, env, monkeypatch, capsys):
    host = dead.removeprefix("http://")
    monkeypatch.setenv("HF_ENDPOINT", f"http://robot:hf_s3cret@{host}")  # a mirror behind a login
    hub = entries(dead)[2]
    with catalog.use(Catalog([hub])):
        assert cli(["weights", "fetch", hub.name]) == 1
        mine = ["weights", "fetch", "my_head", "--url", f"http://robot:s3cret@{host}/my_head.pth", "--sha256", DIGEST]
        assert cli(mine) == 1
        assert cli([*mine, "--offline"]) == 1
        assert cli(["weights", "path", hub.name]) == 1
    err = capsys.readouterr().err
    assert "s3cret" not in err and "robot" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 4 and all(f": {host} is unreachable (" in line for line in lines[:2]), err
    assert f"download it from http://{host}/org/repo/resolve/main/c.pth;" in lines[0]
    assert lines[2].endswith(f"offline mode: not downloading my_head from http://{host}/my_head.pth")
    assert f"(from http://{host}/org/repo/resolve/main/c.pth)" in lines[3]  # `weights path`: the mirror in force
