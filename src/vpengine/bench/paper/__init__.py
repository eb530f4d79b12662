"""``vpengine bench paper``: the VPEngine paper's experiments, each comparison measured side by side in one run.

    E1     shared backbone + N depth heads vs N independent models vs the models one after another
    E2     N detection heads in parallel (the engine) vs one after another
    E3     CUDA MPS off vs on, 4 and 8 heads (--e3-heads)
    E4     rate limits 5-30 Hz against 10 s (--e4-seconds) of 30 Hz input
    E5     a long 30 Hz stream through depth, seg and det: latency, loss, device memory over time
    floor  the engine vs the same models' device time

The engine is the config's (``--config``, ``--set``, as in ``vpengine run``); its heads named depth, seg and det are
the templates the experiments clone. One results file per run, ``paper_{device}[_{tag}].json``, rewritten after each
experiment; ``vpengine bench report`` draws the figures from it.
"""

from __future__ import annotations

import argparse
import contextlib
import time
from typing import Any

from vpengine.arguments import add_overrides_argument, positive_float

EXPERIMENTS = ("E1", "E2", "E3", "E4", "E5", "floor")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        default="bench",
        help="engine config whose heads named depth, seg and det are the templates (default: %(default)s)",
    )
    add_overrides_argument(p, "mode=thread", "a field of the engine config")
    p.add_argument(
        "--experiments",
        default=",".join(EXPERIMENTS),
        help=f"comma-separated subset of {', '.join(EXPERIMENTS)} (default: all)",
    )
    p.add_argument("--heads", default="1,2,4,8", help="head counts of E1 and E2 (default: %(default)s)")
    p.add_argument("--e3-heads", default="4,8", help="head counts of E3, each kind (default: %(default)s)")
    p.add_argument("--frames", type=int, default=100, help="frames per lockstep measurement (default: %(default)s)")
    p.add_argument(
        "--e4-seconds", type=positive_float, default=10.0, help="seconds of 30 Hz input in E4 (default: %(default)s)"
    )
    p.add_argument("--e5-frames", type=int, default=10000, help="frames of the E5 stream (default: %(default)s)")
    p.add_argument(
        "--floor-heads", default="depth,seg,det", help="heads of the floor experiment (default: %(default)s)"
    )
    p.add_argument(
        "--floor-batches",
        default="",
        help="batch sizes (frames of as many cameras) the floor's device times are also taken at on CUDA, e.g. "
        "1,4,8: the models are then compiled and captured for every size up to the largest (default: none)",
    )
    p.add_argument(
        "--results",
        default="copy",
        choices=["copy", "borrow"],
        help="how the caller takes results: its own copies, or read-only views of the output mailboxes "
        "(Engine.wait(copy=False)); the sequential baseline copies with .cpu() either way",
    )
    p.add_argument(
        "--frame-size",
        default=None,
        metavar="WxH",
        help="size of the frames submitted (default: the config's input size); another size measures the boundary "
        "that fits each frame into the engine's canvas and its outputs back into the frame's grid",
    )
    p.add_argument("--tag", default="", help="suffix of the results file name")


def _counts(text: str, flag: str = "--heads", what: str = "head counts") -> list[int]:
    try:
        ns = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"{flag} {text!r}: expected {what} like 1,2,4,8") from None
    if not ns or min(ns) < 1:
        raise ValueError(f"{flag} {text!r}: expected {what} of at least 1, like 1,2,4,8")
    return ns


def _frame_size(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    w, sep, h = text.lower().partition("x")
    if not sep or not w.isdigit() or not h.isdigit() or int(w) < 1 or int(h) < 1:
        raise ValueError(f"--frame-size {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 1920x1080")
    return int(w), int(h)


def main(args: argparse.Namespace) -> int:
    from vpengine.bench.common import machine_info, write_results
    from vpengine.bench.paper import (
        e1_shared_backbone,
        e2_parallel_heads,
        e3_mps,
        e4_rates,
        e5_stream,
        floor,
    )
    from vpengine.bench.paper.harness import Bench, log, mps_daemon

    want = [x.strip() for x in args.experiments.split(",") if x.strip()]
    unknown = [x for x in want if x not in EXPERIMENTS]
    if unknown or not want:
        raise ValueError(f"--experiments {args.experiments!r}: accepted are {', '.join(EXPERIMENTS)}")
    ns = _counts(args.heads)
    e3_ns = tuple(_counts(args.e3_heads, "--e3-heads"))
    kinds = floor.check_kinds(tuple(k.strip() for k in args.floor_heads.split(",") if k.strip()))
    floor_batches = (
        tuple(_counts(args.floor_batches, "--floor-batches", "frame counts")) if args.floor_batches.strip() else ()
    )
    b = Bench.load(args.config, args.overrides, args.frames, args.results == "copy")
    # what each experiment needs, checked before anything starts: a late refusal would waste the runs before it
    needs = {
        "E1": ("depth",),
        "E2": ("det",),
        "E3": ("det", "depth"),
        "E4": ("depth",),
        "E5": e5_stream.HEADS,
    }
    for key in want:
        for kind in kinds if key == "floor" else needs[key]:
            b.head(kind, kind)
    if "E3" in want:
        e3_mps.check(b)
    runs: dict[str, Any] = {
        "E1": lambda imgs: e1_shared_backbone.run(b, imgs, ns),
        "E2": lambda imgs: e2_parallel_heads.run(b, imgs, ns),
        "E3": lambda imgs: e3_mps.run(b, imgs, e3_ns),
        "E4": lambda imgs: e4_rates.run(b, imgs, args.e4_seconds),
        "E5": lambda imgs: e5_stream.run(b, imgs, args.e5_frames),
        "floor": lambda imgs: floor.run(b, imgs, kinds, floor_batches),
    }
    imgs = b.images(size=_frame_size(args.frame_size))
    name = f"paper_{b.device.split(':')[0]}{'_' + args.tag if args.tag else ''}"
    res: dict[str, Any] = {"setup": {**b.setup(), "frame_size": [imgs[0].shape[1], imgs[0].shape[0]]}}
    log(f"machine: {machine_info()}")
    with contextlib.ExitStack() as stack:
        if b.base.mps == "required":  # a daemon this run can reach, started for it if none is
            stack.enter_context(mps_daemon())
        for key in want:
            t = time.monotonic()
            res[key] = runs[key](imgs)
            res[key]["seconds"] = time.monotonic() - t
            # after every experiment: a crash keeps what was measured
            path = write_results(args.out, name, res)
    log(f"-> {path}; figures and tables: vpengine bench report --results {path.parent} --out {path.parent}")
    return 0
