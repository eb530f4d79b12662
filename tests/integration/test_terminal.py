"""What a terminal shows of a command: a reader that goes away (`| head`), log lines kept to what -v asks for.
Each runs the console script in a process of its own, as a terminal's user does."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests_paths import ROOT

TESTS = ROOT / "tests"


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


def test_v_shows_the_engines_and_a_worker_processs_info_lines(tmp_path):
    """The terminal's filter keeps to -v's level, not below it: -v shows INFO, a process-mode worker's too."""
    opts = '{"log_at_build": "an INFO line from the seg worker", "log_at_build_level": "INFO"}'
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(TESTS), os.environ.get("PYTHONPATH")]))}
    p = subprocess.run(
        [sys.executable, "-m", "vpengine", "-v", "run", "-c", "tiny", "-s", "synthetic:64x48@30:2", "--no-progress",
         "--mode", "process", "--set", "heads.seg.model=helpers.faulty:FaultyHead",
         "--set", f"heads.seg.options={opts}", "--set", f"logging.file={tmp_path / 'e.log'}"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path, env=env,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert "engine 'tiny' running" in p.stderr and "an INFO line from the seg worker" in p.stderr, p.stderr


def test_config_show_says_a_config_whose_backend_options_would_not_plan(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("heads: [{name: depth, model: tiny_depth, backend: compile, backend_options: {mod: x}}]\n")
    p = subprocess.run([sys.executable, "-m", "vpengine", "config", "show", str(bad)], capture_output=True, text=True,
                       timeout=120)  # fmt: skip
    assert p.returncode == 1 and "heads.depth.backend_options: bad backend_options for backend 'compile'" in p.stderr
