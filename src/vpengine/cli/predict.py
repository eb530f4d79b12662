"""``vpengine predict SOURCE``: annotated pictures of every head's outputs, for an image, a glob, a folder, a video, a
camera or a shipped sample, with a config that runs anywhere (``tiny``) unless told otherwise.

Every head runs on every frame: the config's rate limits are switched off (and the command says so), because a
picture per frame with some heads missing is not what this command is for; ``vpengine run`` honours them. Each frame
goes in once the previous one is answered by every head (lockstep). Pictures go to a new folder each time,
``runs/predict``, ``runs/predict2``, ... (never into an earlier run's), with ``summary.json`` beside them; with
several cameras (``NAME=SOURCE`` each) every camera's pictures are in a folder of its own, ``<out>/<camera>/``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from vpengine.arguments import add_config_argument, add_overrides_argument, positive_int
from vpengine.cli import prepare_out_dir
from vpengine.cli.run import SOURCE_HELP, SOURCES_HELP
from vpengine.cli.serve import add_serve_arguments, serve_options


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("sources", nargs="*", metavar="[NAME=]SOURCE", help=SOURCE_HELP + ". " + SOURCES_HELP)
    p.add_argument(
        "--source", "-s", action="append", default=[], metavar="[NAME=]SPEC", help="a source, as SOURCE (repeatable)"
    )
    p.add_argument(
        "--topic",
        action="append",
        default=[],
        metavar="[NAME=]TOPIC",
        help="image topic of a bag source; NAME=TOPIC per camera (see vpengine run --help)",
    )
    add_config_argument(p, default="tiny")
    p.add_argument(
        "--out",
        "-o",
        help="output folder (default: the first of runs/predict, runs/predict2, ... that does not exist); refused "
        "if it holds files already",
    )
    p.add_argument("--exist-ok", action="store_true", help="write into an --out folder that exists")
    p.add_argument("--max-frames", type=positive_int, help="stop after this many frames")
    add_overrides_argument(p, "device=cuda")
    p.add_argument("--mode", choices=["process", "thread"], help="override the config's mode")
    p.add_argument("--device", help="override the config's device (cpu, cuda, cuda:N)")
    p.add_argument("--random-weights", action="store_true", help="use random weights (loudly) instead of checkpoints")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_serve_arguments(p)


def next_run_dir(base: str | Path = "runs/predict") -> Path:
    """Create and return the first of ``base``, ``base2``, ``base3``, ... that does not exist yet (created here, so
    that two runs started at once never share one)."""
    base = Path(base)
    base.parent.mkdir(parents=True, exist_ok=True)
    for i in range(1, 1_000_000):
        out = base if i == 1 else base.with_name(f"{base.name}{i}")
        try:
            out.mkdir()
        except FileExistsError:
            continue
        return out
    raise RuntimeError(f"no free folder name left for {str(base)!r}")


def main(args: argparse.Namespace) -> int:
    from vpengine.cli.run import engine_overrides, exit_status, format_summary, parse_sources, run_served
    from vpengine.config import load_config
    from vpengine.io.sinks import AnnotatedSink, per_camera
    from vpengine.named_inputs import config_for_cameras
    from vpengine.pipeline.run import Pipeline, open_sources

    given = [*args.sources, *args.source]
    if not given:
        raise ValueError(
            "give a source: an image, a folder, a glob, a video, a camera (camera:N, /dev/videoN), a stream URL or sample:NAME"
        )
    wanted = parse_sources(given, args.topic)
    cameras = [c for c in wanted if c is not None]
    cfg = config_for_cameras(args.config, cameras or None, engine_overrides(args))
    # every head on every frame: one picture per frame with every head in it
    rates = {"foundation": cfg.foundation_model.rate_hz, **{h.name: h.rate_hz for h in cfg.heads}}
    limited = ", ".join(f"{n} to {hz:g} Hz" for n, hz in rates.items() if hz is not None)
    cfg = load_config(cfg, ["foundation_model.rate_hz=null", *(f"heads.{h.name}.rate_hz=null" for h in cfg.heads)])
    serve = serve_options(args)
    out = prepare_out_dir(args.out, args.exist_ok) if args.out else None  # checked before a camera opens
    with open_sources(wanted) as sources:
        out = out or next_run_dir()  # made once the sources opened: a bad one leaves no empty run folder
        print(
            "rate limits off: every head runs on every frame" + (f" (the config limits {limited})" if limited else ""),
            flush=True,
        )

        def pictures(heads: dict[str, dict[str, Any]], served: dict[str, list[str]]) -> Any:
            # several cameras: one folder of pictures each, out/<camera>/
            return per_camera(served, heads, lambda camera, infos: AnnotatedSink(infos, pictures=out / (camera or "")))

        def report(summary: dict[str, Any]) -> None:  # before a --serve view stays up (Note [Serving on])
            print(format_summary(summary))
            print(f"annotated pictures and summary.json in {out}", flush=True)

        pipe = Pipeline(
            cfg,
            sources if cameras else sources[None],
            out,
            pace="lockstep",
            max_frames=args.max_frames,
            progress=not args.no_progress,
            sink_factories=[pictures],
            folder=False,
        )
        summary = run_served(pipe, serve, report)
    return exit_status(summary, "predict")
