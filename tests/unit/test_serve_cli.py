"""``--serve`` as the CLI sees it before any engine starts: a missing extra, the help text."""

from __future__ import annotations

import importlib.abc
import sys

import pytest

from vpengine.cli.main import build_parser, main


class _Uninstalled(importlib.abc.MetaPathFinder):
    """Makes a module unimportable as an absent one is: ModuleNotFoundError naming it."""

    def __init__(self, name: str) -> None:
        self.name = name

    def find_spec(self, fullname, path=None, target=None):
        if fullname.partition(".")[0] == self.name:
            raise ModuleNotFoundError(f"No module named {fullname!r}", name=fullname)
        return None


@pytest.mark.parametrize("hide", ["hook", "sys.modules"])
def test_serve_without_the_web_extra_names_the_extra_and_the_pip_command(monkeypatch, capsys, hide):
    if hide == "hook":
        monkeypatch.setattr(sys, "meta_path", [_Uninstalled("prometheus_client"), *sys.meta_path])
    for name in [m for m in sys.modules if m.partition(".")[0] == "prometheus_client"]:
        monkeypatch.delitem(sys.modules, name)
    if hide == "sys.modules":
        monkeypatch.setitem(sys.modules, "prometheus_client", None)
    # an engine would start (seconds) before the view does: the extra is checked before
    monkeypatch.setattr("vpengine.engine.Engine.start", lambda self: pytest.fail("the engine started"))
    rc = main(["run", "-c", "tiny", "-s", "synthetic:64x48:2", "--serve", "0", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 1
    assert len(err.splitlines()) == 1, err
    assert "'web'" in err and "pip install 'vpengine[web]'" in err, err


def test_an_address_the_view_cannot_listen_at_is_refused_before_the_engine_starts(monkeypatch, capsys, tmp_path):
    import socket

    monkeypatch.setattr("vpengine.engine.Engine.start", lambda self: pytest.fail("the engine started"))
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        out = tmp_path / "out"
        rc = main(["run", "-c", "tiny", "-s", "synthetic:64x48:2", "--serve", str(port), "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err.startswith(f"vpengine run: error: --serve {port}: cannot listen there (")
    assert not out.exists()  # nothing written that a second try would have to be told to replace


def test_pace_help_says_what_each_pacing_does(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    pace = text[text.rindex("--pace {lockstep,realtime}") :].split(" --fps")[0]  # its entry, not the usage line
    assert "--help" not in pace  # not a pointer to itself
    assert "lockstep:" in pace and "realtime:" in pace and "newest" in pace
