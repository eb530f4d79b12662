"""``vpengine bench``: the benchmark suite. Each benchmark writes a JSON results file (and figures where useful)."""

from __future__ import annotations

import argparse
import importlib

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
    "web": ("vpengine.bench.web", "the live view's cost: E5's 30 Hz stream with and without a viewer"),
    "report": ("vpengine.bench.report", "summary.md and summary.png from a folder of results files"),
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="bench", metavar="BENCH", required=True)
    for name, (module, help_text) in BENCHES.items():
        sp = sub.add_parser(name, help=help_text, description=help_text)
        sp.set_defaults(_bench=module)
        if name != "report":
            sp.add_argument("--out", default="benchmarks/results", help="folder for the results JSON")
        importlib.import_module(module).add_arguments(sp)


def main(args: argparse.Namespace) -> int:
    return int(importlib.import_module(args._bench).main(args) or 0)
