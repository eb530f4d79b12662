"""Command-line interface."""

from __future__ import annotations

import argparse


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
