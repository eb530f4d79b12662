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


DAMAGED_VIDEO = """
import os, sys
{set_level}
import cv2, numpy as np
path = sys.argv[1]
w = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"MJPG"), 10, (160, 120))
rng = np.random.default_rng(0)
for _ in range(20):
    w.write(rng.integers(0, 256, (120, 160, 3), dtype=np.uint8))
w.release()
data = bytearray(open(path, "rb").read())
data[len(data) // 2 : len(data) // 2 + 4000] = bytes(4000)  # a damaged stretch mid-file
open(path, "wb").write(bytes(data))
cap = cv2.VideoCapture(path)
n = 0
while cap.read()[0]:
    n += 1
print(n)
"""


@pytest.mark.parametrize(("argv", "level"), [(["config", "list"], "8"), (["config", "list", "-v"], None)])
def test_ffmpegs_own_lines_are_kept_to_fatal_ones_unless_v(monkeypatch, argv, level):
    """Without -v the CLI asks OpenCV's FFmpeg for fatal errors only (its line per damaged packet would run through
    the progress bar, naming no file); with -v, or a level the user set, it is left alone."""
    monkeypatch.delenv("OPENCV_FFMPEG_LOGLEVEL", raising=False)
    monkeypatch.setattr(cli_main.logging, "basicConfig", lambda level, **kw: None)
    assert cli_main.main(argv) == 0
    assert cli_main.os.environ.get("OPENCV_FFMPEG_LOGLEVEL") == level
    monkeypatch.setenv("OPENCV_FFMPEG_LOGLEVEL", "32")
    assert cli_main.main(argv) == 0
    assert cli_main.os.environ["OPENCV_FFMPEG_LOGLEVEL"] == "32"


def test_that_level_keeps_ffmpegs_lines_about_a_damaged_video_off_stderr(tmp_path):
    """What the level does: a video with a damaged stretch decodes to the same frames, and FFmpeg's lines about it
    reach descriptor 2 at OpenCV's default level and not at the CLI's (set, as the CLI does, before a video opens)."""
    runs = {}
    for name, set_level in (
        ("default", ""),
        ("cli", f"os.environ['OPENCV_FFMPEG_LOGLEVEL'] = '{cli_main._AV_LOG_FATAL}'"),
    ):
        env = {k: v for k, v in cli_main.os.environ.items() if k != "OPENCV_FFMPEG_LOGLEVEL"}
        code = DAMAGED_VIDEO.format(set_level=set_level)
        runs[name] = subprocess.run(
            [sys.executable, "-c", code, str(tmp_path / f"{name}.avi")],
            capture_output=True, text=True, timeout=60, check=True, env=env,
        )  # fmt: skip
    assert runs["default"].stdout == runs["cli"].stdout and int(runs["cli"].stdout) > 10
    assert "[mjpeg @" in runs["default"].stderr
    assert runs["cli"].stderr == ""
