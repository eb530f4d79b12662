"""Command-line interface."""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path


def add_overrides_argument(
    p: argparse.ArgumentParser, example: str = "heads.depth.rate_hz=5", what: str = "a config field"
) -> None:
    """``--set KEY=VALUE`` (repeatable) into ``args.overrides``: the one spelling every command uses."""
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=f"override {what}, e.g. --set {example} (repeatable)",
    )


def add_config_argument(p: argparse.ArgumentParser, default: str | None = None) -> None:
    """``--config/-c``: a shipped config's name or a file (``load_config`` resolves both)."""
    p.add_argument(
        "--config",
        "-c",
        required=default is None,
        default=default,
        help="engine config: a shipped config's name (`vpengine config list`) or a YAML/JSON file"
        + (f" (default: {default})" if default else ""),
    )


def positive_int(text: str) -> int:
    """An argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """An argparse type: a finite number > 0 (no 0, negative, nan or inf)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number above 0, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a number above 0, got {text!r}")
    return value


def prepare_out_dir(path: str | Path, exist_ok: bool, what: str = "--out") -> Path:
    """Create the output folder of a run before the engine starts, or fail in one line: a folder that holds files
    already (unless ``exist_ok``: same-named files are then replaced, the others stay), a file in the way, or a
    place that cannot be written."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{what} {str(out)!r} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not exist_ok:
        raise ValueError(
            f"{what} {str(out)!r} exists already and holds files; give a new folder, or add --exist-ok to write "
            f"into it (files of the same names are replaced, the others stay)"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
        _probe(out)
    except OSError as e:
        raise ValueError(f"cannot write {what} {str(out)!r}: {e.strerror or e}") from None
    return out


def prepare_out_file(path: str | Path, exist_ok: bool, what: str, replaceable: bool = True) -> Path:
    """Check that a run's output file (a video, a bag) can be made before the engine starts: it does not exist
    (unless ``exist_ok`` and ``replaceable``) and its folder can be created and written."""
    out = Path(path)
    if out.exists() and not (exist_ok and replaceable and out.is_file()):
        hint = ", or add --exist-ok to replace it" if replaceable and out.is_file() else " (never overwritten)"
        raise ValueError(f"{what} {str(out)!r} exists already; give a new name{hint}")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        _probe(out.parent)
    except OSError as e:
        raise ValueError(f"cannot write {what} {str(out)!r}: {e.strerror or e}") from None
    return out


def _probe(folder: Path) -> None:
    """Raise OSError unless a file can be created in ``folder`` (permissions alone do not tell: root, read-only
    mounts)."""
    with tempfile.TemporaryFile(dir=folder):
        pass
