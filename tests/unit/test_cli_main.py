"""The console script's own front: `python -m vpengine`, and -v anywhere on the line."""

from __future__ import annotations

import os
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


@pytest.mark.parametrize("command", [["config", "show", "dinov2s_depth_seg_det"], ["config", "list"]])
def test_a_reader_that_goes_away_ends_the_command_quietly(command):
    """`vpengine config list | head -1`: the pipe closes under the command; it ends as a program killed by SIGPIPE
    would (141), with no traceback, whether the command flushes its lines (config show) or leaves them buffered
    for the interpreter's exit (config list; buffered as a terminal's user gets it, without PYTHONUNBUFFERED)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    p = subprocess.Popen(
        [sys.executable, "-m", "vpengine", *command],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert p.stdout is not None and p.stderr is not None
    p.stdout.close()  # the reader is gone before the first line
    err = p.stderr.read()
    assert p.wait(timeout=60) == 141 and "Traceback" not in err and "BrokenPipe" not in err, err
