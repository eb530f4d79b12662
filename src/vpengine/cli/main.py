"""``vpengine``: one console script, one subcommand per job. Subcommands import their heavy modules lazily."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import sys

# subcommand -> module with add_arguments(parser) and main(args) -> int
COMMANDS = {
    "run": ("vpengine.cli.run", "run a pipeline on a video, an image folder, a camera or a synthetic scene"),
    "predict": (
        "vpengine.cli.predict",
        "annotated pictures of every head's outputs for images, a video or a camera",
    ),
    "config": ("vpengine.cli.configs", "the configs that ship with vpengine: list, show"),
    "info": ("vpengine.cli.info", "versions, devices, CUDA MPS daemon, model catalog"),
    "bench": (
        "vpengine.cli.bench",
        "benchmarks: the paper's experiments, cameras, heads, steering, hop, pipeline, resources, web, report",
    ),
    "export": ("vpengine.cli.export", "export a model of a config to ONNX"),
    "weights": ("vpengine.cli.weights", "checkpoint catalog: list, fetch, verify, path"),
    "train": (
        "vpengine.cli.train",
        "train a detection head on frozen foundation-model features (COCO boxes)",
    ),
    "mps": ("vpengine.cli.mps", "start, stop or check a CUDA MPS control daemon (private pipe directory)"),
    "ros2": ("vpengine.cli.ros2", "the engine on a ROS 2 graph through a CycloneDDS bridge"),
}

# top-level module of an optional dependency -> the extra that installs it
EXTRAS = {
    "cyclonedds": "ros2",
    "rosbags": "ros2",
    "mcap": "ros2",
    "onnx": "onnx",
    "onnxruntime": "onnx",
    "onnxscript": "onnx",
    "cuda": "cuda",
    "pynvml": "cuda",
    "matplotlib": "plots",
    "prometheus_client": "web",
}


def build_parser() -> argparse.ArgumentParser:
    from vpengine import __version__

    p = argparse.ArgumentParser(prog="vpengine", description="One foundation model per frame, many heads in parallel.")
    p.add_argument("--version", action="version", version=f"vpengine {__version__}")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        sp = sub.add_parser(name, help=help_text, description=help_text)
        sp.set_defaults(_module=module)
        importlib.import_module(module).add_arguments(sp)
    return p


def _take_verbose(argv: list[str]) -> tuple[list[str], int]:
    """``-v``/``-vv``/``--verbose`` anywhere before a ``--``, counted and taken out, so that they work after a
    subcommand (``vpengine run ... -v``, ``vpengine config list -v``) as well as before it."""
    rest: list[str] = []
    count = 0
    for i, arg in enumerate(argv):
        if arg == "--":
            return rest + argv[i:], count
        if arg == "--verbose":
            count += 1
        elif len(arg) > 1 and arg[0] == "-" and set(arg[1:]) == {"v"}:
            count += len(arg) - 1
        else:
            rest.append(arg)
    return rest, count


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv, verbose = _take_verbose(sys.argv[1:] if argv is None else list(argv))
    args = parser.parse_args(argv)
    args.verbose += verbose  # what argparse saw as well (an abbreviation such as --verb before the subcommand)
    if not getattr(args, "_module", None):
        parser.print_help()
        return 2
    level = logging.WARNING if args.verbose == 0 else logging.INFO if args.verbose == 1 else logging.DEBUG
    had = list(logging.getLogger().handlers)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # the terminal shows what -v asks for, and a long start's progress (Note [Start progress]); logging.file may
    # lower the vpengine logger for its own sake, and its records must not reach the terminal through that. Only
    # on the handler made here (a host program's, or a test runner's, are theirs)
    for handler in logging.getLogger().handlers:
        if handler not in had:
            handler.addFilter(lambda r, level=level: r.levelno >= level or r.name == "vpengine.start")
    if level > logging.INFO:
        logging.getLogger("vpengine.start").setLevel(logging.INFO)
    try:
        code = int(importlib.import_module(args._module).main(args) or 0)
        sys.stdout.flush()  # here, where a reader gone away is caught below, not at the interpreter's exit
        return code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        if not _stdout_gone():
            raise  # another pipe (a worker's, a socket): a failure of its own
        # the reader of the output went away (`| head`): nothing more to say, and no traceback for it
        with contextlib.suppress(OSError):  # the interpreter's flush at exit would fail again
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # as a program killed by SIGPIPE: 128 + 13
    except ModuleNotFoundError as e:
        top = (e.name or "").partition(".")[0]
        extra = EXTRAS.get(top)
        if extra is None or args.verbose >= 2:
            raise
        print(
            f"vpengine {args.command}: error: this needs the optional extra '{extra}' ({top} is not "
            f"installed): pip install 'vpengine[{extra}]'",
            file=sys.stderr,
        )
        return 1
    except (ValueError, KeyError, FileNotFoundError, RuntimeError) as e:
        if args.verbose >= 2:
            raise
        print(f"vpengine {args.command}: error: {e}", file=sys.stderr)
        return 1


def _stdout_gone() -> bool:
    """Whether standard output's reader went away: its flush fails as the pipe is broken."""
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        return True
    except (OSError, ValueError):  # closed, or another failure: not a reader gone
        pass
    return False


if __name__ == "__main__":
    sys.exit(main())
