"""Every `vpengine weights` command that README.md and docs/weights.md show works as written, from an empty folder
and an empty cache, with the network replaced by one HTTP server on 127.0.0.1: it serves a stand-in for each file
of the shipped catalog (plain https URLs answered by it through urllib's opener, Hub files through $HF_ENDPOINT), with
the same kind of digest as the real entry (published or none), so the commands meet the catalog as it ships.
"""

from __future__ import annotations

import hashlib
import http.server
import re
import shlex
import threading
import urllib.parse
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from helpers.https import https_served_by
from tests_paths import ROOT
from vpengine.cli.main import main as cli
from vpengine.models import catalog
from vpengine.models.catalog import Catalog

pytestmark = pytest.mark.timeout(120)

DOCS = [ROOT / "README.md", ROOT / "docs" / "weights.md"]
#: The one placeholder entry: one without a published digest, the case the flags are about.
NAME = "dinov2_vits14_ade20k_linear_head"
CUSTOM_PATH = "/my_head.pth"


def body(name: str) -> bytes:
    return f"stand-in for {name}\n".encode() * 64


def shown_commands() -> list[str]:
    """`vpengine weights ...` in code blocks (one a line, comments cut) and in inline code, in document order."""
    found = []
    for doc in DOCS:
        text = doc.read_text()
        for block in re.findall(r"```(?:bash|sh)\n(.*?)```", text, re.S):
            found += [ln.split(" #")[0].strip() for ln in block.splitlines() if ln.startswith("vpengine weights ")]
        text = re.sub(r"```.*?```", "", text, flags=re.S)
        found += [c.strip() for c in re.findall(r"`(vpengine weights [^`]+)`", text.replace("\n", " "))]
    return found


@pytest.fixture
def net(tmp_path, monkeypatch) -> Iterator[dict[str, bytes]]:
    """The stand-in network: path -> body, served with the headers the Hub sends (harmless for plain URLs)."""
    files: dict[str, bytes] = {}

    class Handler(http.server.BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def answer(self, with_body: bool) -> None:
            data = files.get(self.path)
            if data is None:
                self.send_response(404)
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            self.send_response(200)
            self.send_header("X-Repo-Commit", "0123456789abcdef0123456789abcdef01234567")
            self.send_header("ETag", f'"{hashlib.sha256(data).hexdigest()}"')
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            if with_body:
                self.wfile.write(data)

        def do_HEAD(self) -> None:
            self.answer(False)

        def do_GET(self) -> None:
            self.answer(True)

        def log_message(self, *args: object) -> None:
            pass

    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    url = f"http://127.0.0.1:{httpd.server_address[1]}"
    thread = threading.Thread(target=httpd.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    entries = []
    for e in catalog.shipped():
        data = body(e.name)
        path = urllib.parse.urlsplit(e.url).path
        files[path] = data
        entries.append(
            replace(
                e,
                sha256=hashlib.sha256(data).hexdigest() if e.sha256 else None,
                size=len(data) if e.size else None,
            )
        )
    files[CUSTOM_PATH] = body("my_head")
    files["url"] = url.encode()
    monkeypatch.setenv("HF_ENDPOINT", url)
    monkeypatch.setenv("VPENGINE_CACHE", str(tmp_path / "cache"))
    for var in ("VPENGINE_OFFLINE", "HF_HUB_OFFLINE", "VPENGINE_CATALOG"):
        monkeypatch.delenv(var, raising=False)
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.chdir(empty)  # as a user would, not from a clone
    try:
        with catalog.use(Catalog(entries)), https_served_by(url):
            yield files
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(5)


def test_the_docs_show_the_commands_this_test_runs():
    shown = shown_commands()
    assert "vpengine weights fetch depth_anything_v2_vits dinov2_vits14_ade20k_linear_head" in shown  # README
    assert any(c.startswith("vpengine weights fetch --config ") for c in shown)
    assert any("--url" in c for c in shown) and any(c.startswith("vpengine weights verify") for c in shown)


def test_every_weights_command_shown_works_as_written(net, tmp_path, capsys):
    url = net["url"].decode()
    fills = {
        "NAME...": NAME,
        "NAME": NAME,
        "ACTION": "list",
        "DIR": str(tmp_path / "other-cache"),
        "HEX": hashlib.sha256(body(NAME)).hexdigest(),
        "<hex>": hashlib.sha256(body("my_head")).hexdigest(),
        "https://example.org/my_head.pth": url + CUSTOM_PATH,
    }
    ran = []
    for command in shown_commands():
        argv = shlex.split(command)[1:]
        argv = [fills.get(a, a) for a in argv]
        rc = cli([*argv, "--no-progress"] if argv[1] in ("fetch", "verify") else argv)
        out = capsys.readouterr()
        assert rc == 0, f"`{command}` exited {rc}:\n{out.out}\n{out.err}"
        assert "Traceback" not in out.err
        ran.append(command)
    assert len(ran) >= 8
    # What the README's fetch brought is in the cache and verified, the no-digest file pinned on first use.
    assert cli(["weights", "verify", "depth_anything_v2_vits", NAME, "--no-progress"]) == 0
    assert catalog.effective(catalog.find(NAME), Path(tmp_path / "cache")).sha256 is not None
