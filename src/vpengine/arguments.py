"""Command-line argument helpers that ``vpengine``'s commands (cli/) and its benchmarks (bench/) share.

They live below both so that a benchmark needs nothing of cli/: cli/ loads the benchmarks by name, and an import
back would close a circle (tests/unit/test_imports.py).
"""

from __future__ import annotations

import argparse
import math


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
