"""``vpengine config list | show NAME``: the configs that ship with the package (any ``-c`` takes their names)."""

from __future__ import annotations

import argparse
import sys


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    sub.add_parser("list", help="the shipped configs, by name, with what each is for")
    show = sub.add_parser("show", help="print a config (shipped name or path) as written, with its comments")
    show.add_argument("name", help="a shipped config's name (e.g. tiny) or a config file")


def main(args: argparse.Namespace) -> int:
    from vpengine import configs

    if args.action == "list":
        width = max(map(len, configs.names()))
        for name in configs.names():
            print(f"{name:{width}s}  {configs.describe(name)}")
        return 0
    from vpengine.config import ConfigError, load_config

    path = configs.resolve(args.name)
    print(f"# {path}")
    print(path.read_text(), end="", flush=True)
    try:  # shown as written, and said when it would not load (a file being written, a copy to edit)
        from vpengine.runtime.plan import check_backend_options

        check_backend_options(load_config(path))  # checked while planning, where the backends are imported
    except ConfigError as e:
        print(f"vpengine config show: error: {e}", file=sys.stderr)
        return 1
    return 0
