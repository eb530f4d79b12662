"""The console script's own front: `python -m vpengine`, and -v anywhere on the line."""

from __future__ import annotations

import subprocess
import sys

import pytest

from vpengine import __version__
from vpengine.cli import main as cli_main


def test_python_dash_m_vpengine_is_the_console_script():
    out = subprocess.run(
        [sys.executable, "-m", "vpengine", "--version"], capture_output=True, text=True, timeout=60, check=True
    )
    assert out.stdout.strip() == f"vpengine {__version__}"


@pytest.mark.parametrize(
    ("argv", "rest", "count"),
    [
        (["-v", "run", "-c", "tiny"], ["run", "-c", "tiny"], 1),
        (["run", "-c", "tiny", "-vv"], ["run", "-c", "tiny"], 2),
        (["config", "list", "--verbose", "-v"], ["config", "list"], 2),
        (["run", "--", "-v"], ["run", "--", "-v"], 0),  # after "--" it is an argument, not a flag
        (["run", "--set", "x=-v", "-vx"], ["run", "--set", "x=-v", "-vx"], 0),
    ],
)
def test_verbose_counts_before_and_after_the_subcommand(argv, rest, count):
    assert cli_main._take_verbose(argv) == (rest, count)


def test_a_nested_subcommand_takes_v_after_it(capsys, monkeypatch):
    seen = []
    monkeypatch.setattr(cli_main.logging, "basicConfig", lambda level, **kw: seen.append(level))
    assert cli_main.main(["config", "list", "-vv"]) == 0
    assert seen == [cli_main.logging.DEBUG] and "tiny" in capsys.readouterr().out


def test_an_abbreviated_verbose_before_the_subcommand_still_counts(monkeypatch):
    seen = []
    monkeypatch.setattr(cli_main.logging, "basicConfig", lambda level, **kw: seen.append(level))
    assert cli_main.main(["--verb", "config", "list", "-v"]) == 0
    assert seen == [cli_main.logging.DEBUG]


def test_help_and_usage_errors_import_no_torch():
    """``vpengine --help``, a subcommand's help and a mistyped argument answer at once: the parser (every
    benchmark's arguments included) imports no torch, which takes seconds on a small machine."""
    code = (
        "import sys\n"
        "from vpengine.cli.main import build_parser\n"
        "p = build_parser()\n"
        "for argv in (['bench', 'hop', '--help'], ['run', '-c', 'tiny', '--no-such-flag']):\n"
        "    try:\n"
        "        p.parse_args(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "print('torch' in sys.modules)\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.split()[-1] == "False", p.stdout[-500:]
    assert "--no-such-flag" in p.stderr  # the usage error was answered
