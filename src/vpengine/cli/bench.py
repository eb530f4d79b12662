"""``vpengine bench``: the benchmark suite. Each benchmark writes a JSON results file (and figures where useful)
under ``--out``: by default a new folder named for the run in the current folder, never a tracked one such as a
clone's ``benchmarks/results`` (results land there when asked for, ``--out benchmarks/results/<GPU kind>``)."""

from __future__ import annotations

import argparse
import importlib
import time
from pathlib import Path

BENCHES = {
    "hop": ("vpengine.bench.hop", "mailbox hop latency: publish -> reader woken -> slot pinned"),
    "pipeline": ("vpengine.bench.pipeline", "tiny pipeline throughput in process and thread mode"),
    "ros2-bridge": (
        "vpengine.bench.ros2_bridge",
        "ROS 2 DDS bridge: 1080p frames in at 30 Hz, all outputs out",
    ),
    "resources": ("vpengine.bench.resources", "GPU: device memory per extra head, CPU idle and at 30 Hz"),
    "paper": ("vpengine.bench.paper", "the VPEngine paper's experiments E1-E5 and the device-time floor"),
    "cameras": ("vpengine.bench.cameras", "several cameras on one batched engine against one engine a camera"),
    "heads": ("vpengine.bench.heads", "heads added and removed while a stream runs: gaps, time, device memory"),
    "steer": ("vpengine.bench.steer", "priorities under overload and how soon a priority change takes effect"),
    "web": ("vpengine.bench.web", "the live view's cost: E5's 30 Hz stream with and without a viewer"),
    "report": ("vpengine.bench.report", "summary.md and summary.png from a folder of results files"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="bench", metavar="BENCH", required=True)
    for name, (module, help_text) in BENCHES.items():
        sp = sub.add_parser(name, help=help_text, description=help_text)
        sp.set_defaults(_bench=module)
        what = "summary.md and summary.png" if name == "report" else "the results JSON (and figures)"
        sp.add_argument(
            "--out",
            "-o",
            metavar="DIR",
            help=f"folder for {what}, made if missing (default: a new folder bench-{name}-<date>-<time> here)",
        )
        importlib.import_module(module).add_arguments(sp)


def out_folder(bench: str, out: str | None, now: float | None = None) -> Path:
    """The folder a benchmark writes to, made: ``out``, or a new ``bench-<bench>-<YYYYmmdd-HHMMSS>[-N]`` in the
    current folder. ValueError when ``out`` is a file."""
    if out is not None:
        path = Path(out)
        if path.exists() and not path.is_dir():
            raise ValueError(f"--out {out!r} is a file; give a folder (made if missing)")
        path.mkdir(parents=True, exist_ok=True)
        return path
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(now))
    for n in range(1, 1000):
        path = Path(f"bench-{bench}-{stamp}" + (f"-{n}" if n > 1 else ""))
        try:
            path.mkdir()
        except FileExistsError:  # another run in the same second
            continue
        return path
    raise ValueError(f"no free folder name bench-{bench}-{stamp}-N here; give --out")


def main(args: argparse.Namespace) -> int:
    if not getattr(args, "single", None):  # `resources --single` is one measurement of a parent run: stdout only
        args.out = str(out_folder(args.bench, args.out))
    return int(importlib.import_module(args._bench).main(args) or 0)
