"""What a terminal shows of a command: a reader that goes away (`| head`), log lines kept to what -v asks for.
Each runs the console script in a process of its own, as a terminal's user does."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


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


def test_logging_file_keeps_the_engines_info_lines_off_a_terminal_without_v(tmp_path):
    """logging.file lowers the vpengine logger so the file gets INFO; the terminal (a run without -v) still shows
    warnings only, a long start's progress aside."""
    log = tmp_path / "engine.log"
    p = subprocess.run(
        [sys.executable, "-m", "vpengine", "run", "-c", "tiny", "-s", "synthetic:64x48@30:2", "--no-progress",
         "--mode", "thread", "--set", f"logging.file={log}"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert "engine 'tiny' running" in log.read_text() and "engine 'tiny' running" not in p.stderr, p.stderr
