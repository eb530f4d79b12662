"""``vpengine run``: a pipeline (:mod:`vpengine.pipeline`) over a video, an image folder, a camera or the built-in
synthetic scene, from the command line: its arguments, the checks of its outputs before the engine starts, and the
printed summary.

Pacing: ``lockstep`` (default for files) or ``realtime`` (default for cameras and the synthetic scene), as
:mod:`vpengine.pipeline.run` describes. Several cameras: ``--source NAME=SPEC`` for each (Note [Several sources] in
``vpengine.pipeline.pacing``). Every output is checked before the engine starts; Ctrl-C ends the run after the frame
in hand and still prints and writes the summary (Note [Ctrl-C] in ``vpengine.pipeline.pacing``). With ``--serve``,
the live view of a run that ends on its own stays up after the summary until Ctrl-C (Note [Serving on] in
``vpengine.cli.serve``).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vpengine.arguments import add_config_argument, add_overrides_argument, positive_float, positive_int
from vpengine.cli import prepare_out_dir, prepare_out_file
from vpengine.cli.serve import ServeOptions, add_serve_arguments, keep_serving, serve_options, serving

if TYPE_CHECKING:  # the pipeline imports the engine (and torch): only once a command runs, not for --help
    from vpengine.engine.results import Result
    from vpengine.io.base import Source
    from vpengine.pipeline.run import Pipeline
    from vpengine.ros2.messages import Header

SOURCE_HELP = (
    "an image, a folder or a glob of images ('frames/*.jpg'), a video file, a rosbag2 bag (folder or .mcap/.db3), "
    "a camera (camera:N, or its device: /dev/video0, /dev/v4l/by-id/...), a stream URL (rtsp://, http://, udp://...), "
    "a GStreamer pipeline (gst:... ! appsink), sample:street or sample:cheetah (shipped with vpengine), or "
    "synthetic[:WxH][@FPS][:FRAMES]"
)


SOURCES_HELP = (
    "Several cameras: NAME=SPEC for each, repeated (e.g. front=camera:0 rear=camera:1); the engine's cameras are "
    "those names and each camera's outputs get a folder of their own (run: DIR/<camera>/<head>/)"
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_argument(p)
    p.add_argument(
        "--source",
        "-s",
        action="append",
        metavar="[NAME=]SPEC",
        help=SOURCE_HELP + " (default: synthetic). " + SOURCES_HELP,
    )
    p.add_argument(
        "--topic",
        action="append",
        metavar="[NAME=]TOPIC",
        help="image topic of a bag source (sensor_msgs/Image or CompressedImage); NAME=TOPIC for camera NAME's "
        "source, or NAME=TOPIC repeated with one bag source: a camera per topic",
    )
    p.add_argument(
        "--strict",
        action="store_true",
        help="stop at a bag's first bad message (default: skip it, log it, list it in the summary)",
    )
    p.add_argument("--out-bag", help="also record every head's outputs to this new rosbag2 bag (ROS 2 message types)")
    p.add_argument("--bag-storage", choices=["mcap", "sqlite3"], default="mcap", help="--out-bag storage")
    p.add_argument(
        "--bag-distro",
        choices=["humble", "jazzy"],
        default="jazzy",
        help="--out-bag message definitions and bag version (humble: v8, jazzy: v9)",
    )
    p.add_argument(
        "--out",
        "-o",
        help="output folder (per-head outputs and summary.json), refused if it holds files already; omit to write "
        "nothing",
    )
    p.add_argument("--exist-ok", action="store_true", help="write into an --out folder (or over a --video) that exists")
    add_overrides_argument(p, "heads.depth.rate_hz=5")
    p.add_argument(
        "--pace",
        choices=["lockstep", "realtime"],
        help="lockstep: the next frame goes in once every head has answered the last, nothing skipped (default for "
        "files, folders, bags); realtime: frames go in at the source's rate and models take the newest, skipped "
        "frames counted (default for cameras and synthetic)",
    )
    p.add_argument(
        "--fps",
        type=positive_float,
        help="realtime pace in Hz and the rate images are stamped at (default: the source's own rate, else 30; a "
        "camera paces itself unless given)",
    )
    p.add_argument("--max-frames", type=positive_int, help="stop after this many frames")
    p.add_argument("--save-every", type=positive_int, default=1, help="write every Nth output per head (default: all)")
    p.add_argument(
        "--depth-format",
        choices=["png16", "npy"],
        default="png16",
        help="depth files: 16-bit PNG with its scale in depth_scale.jsonl (default; Note [Depth PNG]) or float32 .npy",
    )
    p.add_argument("--viz", action="store_true", help="also write pictures: depth with a colour bar, overlays, boxes")
    p.add_argument(
        "--video",
        help="also write an annotated mp4: the input and every head side by side, one frame per frame (.mp4, .avi, "
        ".m4v, .mkv, .mov: H.264 where an encoder is there; .webm: VP8)",
    )
    p.add_argument("--mode", choices=["process", "thread"], help="override the config's mode")
    p.add_argument("--device", help="override the config's device (cpu, cuda, cuda:N)")
    p.add_argument("--random-weights", action="store_true", help="use random weights (loudly) instead of checkpoints")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_serve_arguments(p)


def run_served(pipe: Pipeline, serve: ServeOptions | None, report: Callable[[dict[str, Any]], None]) -> dict[str, Any]:
    """Run ``pipe`` with its live view while it runs (``serve``, drawing on the pipeline's recent frames); ``report``
    gets the summary once the run is over (outputs and summary.json written). The view of a run that ended on its
    own then stays up, on the idle engine, until Ctrl-C or SIGTERM (Note [Serving on] in ``vpengine.cli.serve``)."""
    with pipe, serving(serve, pipe.engine, pipe.frames.frame, pipe.config.input.color) as server:
        summary = pipe.run()
        report(summary)
        if serve is not None and not summary["interrupted"]:
            keep_serving(serve, server)
    return summary


def format_summary(s: dict[str, Any], listed: bool = True) -> str:
    """The run's summary table and notes; ``listed``: summary.json was written (with --out), where the notes point."""
    missed = f"; camera frames a newer one replaced: {s['source_missed']}" if s.get("source_missed") else ""
    stopped = "interrupted after " if s.get("interrupted") else ""
    flight = f", {s['in_flight']} frames a camera in flight" if s.get("in_flight", 1) > 1 else ""
    cameras = s.get("cameras") or {}
    each = ", ".join(f"{c} {x['frames_submitted']}" for c, x in cameras.items())
    each = f" ({each})" if each else ""
    w = max([14] + [len(m["entry"]) for x in cameras.values() for m in x["models"].values()])
    lines = [
        f"{stopped}{s['frames_submitted']} frames{each} in {s['wall_s']:.1f} s ({s['input_hz']:.1f} Hz in, "
        f"{s['pace']}{flight}, {s['mode']} mode on {s['device']}{missed})",
        f"{'model':{w}s} {'target':>7s} {'achieved':>9s} {'runs':>6s} {'skipped':>8s} {'dropped':>8s} "
        f"{'errors':>6s} {'p50 ms':>8s} {'p99 ms':>8s}",
    ]

    def f(v: Any) -> str:
        return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.1f}"

    def row(name: str, m: dict[str, Any], target: float | None = None) -> str:
        lat = m.get("e2e_latency_ms") or m["latency_ms"]
        target = m["target_hz"] if target is None else target
        tgt = "max" if target is None else f"{target:g}"
        return (
            f"{name:{w}s} {tgt:>7s} {m['achieved_hz']:9.1f} {m['runs']:6d} {m['skipped']:8d} "
            f"{m['dropped']:8d} {m['errors']:6d} {f(lat['p50']):>8s} {f(lat['p99']):>8s}"
        )

    def total_target(name: str, m: dict[str, Any]) -> float | None:
        """A model's target over all its cameras, as its achieved rate is summed over them: each lane's summed."""
        lanes = [x["models"][name]["target_hz"] for x in cameras.values() if name in x["models"]]
        return sum(lanes) if lanes and None not in lanes else m["target_hz"]

    lines += [row(name, m, total_target(name, m)) for name, m in s["models"].items()]
    for x in cameras.values():  # each camera's share, named by its lane's entry, as rate commands name it
        lines += [row(m["entry"], m) for m in x["models"].values()]
    lines.append("(latency: submit -> result for heads; model time for the foundation model)")
    if s.get("pace") == "lockstep" and any(m["target_hz"] for m in s["models"].values()):
        lines.append("(a target in lockstep is per second of the source's time; achieved is per second of the run)")
    where = "listed in summary.json" if listed else "-o DIR lists them in its summary.json"
    skipped = s.get("inputs_skipped") or []
    images = [x for x in skipped if "message" not in x]
    if images:
        lines.append(f"images skipped as unreadable: {len(images)} ({where})")
    if len(skipped) > len(images):  # a bag's messages that are no image it can read (docs/ros2.md)
        lines.append(f"bad messages skipped: {len(skipped) - len(images)} ({where})")
    if s.get("inputs_partial"):
        lines.append(f"inputs truncated, decoded partially: {len(s['inputs_partial'])} ({where})")
    unwritten = {n: m["results_unwritten"] for n, m in s["models"].items() if m.get("results_unwritten")}
    if unwritten:
        lines.append(
            "results not written, the output writer being behind the live source: "
            + ", ".join(f"{n} {k}" for n, k in unwritten.items())
        )
    return "\n".join(lines)


def engine_overrides(args: argparse.Namespace) -> list[str]:
    """The config overrides of the options ``run`` and ``predict`` share."""
    overrides = list(args.overrides)
    if args.mode:
        overrides.append(f"mode={args.mode}")
    if args.device:
        overrides.append(f"device={args.device}")
    if args.random_weights:
        overrides.append("weights.random_weights=true")
    return overrides


def parse_sources(sources: Sequence[str], topics: Sequence[str]) -> dict[str | None, tuple[str, str | None]]:
    """``--source`` and ``--topic`` values -> camera name -> (source spec, bag topic); the key None is the one
    unnamed source of a one-camera run; several unnamed ones are refused (a shell glob of images would otherwise
    lose all but one, silently).
    ``NAME=SPEC`` names a source's camera (a path that exists is never read as a name); ``--topic NAME=TOPIC`` gives camera NAME's bag topic, and with one unnamed bag source, several of
    them make one camera of each topic. ValueError naming what does not fit."""
    from vpengine.named_inputs import split_camera

    named = [(None, s) if Path(s).exists() else split_camera(s) for s in sources]
    if len(named) > 1 and not any(n for n, _ in named):
        shown = ", ".join(repr(s) for s in list(sources)[:3]) + (", ..." if len(sources) > 3 else "")
        raise ValueError(
            f"{len(sources)} sources without camera names ({shown}): a run reads one source per camera. For a "
            "sequence of images give their folder or a quoted glob ('frames/*.jpg': quoted, the shell leaves it to "
            "vpengine); for several cameras name each: NAME=SPEC (front=a.mp4 rear=b.mp4)"
        )
    tops = [split_camera(t) for t in topics]
    if len(tops) > 1 and not any(n for n, _ in tops):
        raise ValueError(f"--topic {list(topics)}: one bag topic a camera; name each camera's: --topic NAME=TOPIC")
    if len(named) == 1 and named[0][0] is None:
        spec = named[0][1]
        if not any(n for n, _ in tops):  # today's one camera
            return {None: (spec, tops[0][1] if tops else None)}
        if not all(n for n, _ in tops):
            raise ValueError(f"--topic {[t for t in topics]}: name the camera of every topic, NAME=TOPIC, or of none")
        _unique([n for n, _ in tops], "--topic")
        return {n: (spec, t) for n, t in tops}  # one bag, a camera per topic
    if not all(n for n, _ in named):
        raise ValueError(
            f"--source {list(sources)}: with several cameras, name each source's camera: --source NAME=SPEC "
            "(e.g. --source front=camera:0 --source rear=camera:1)"
        )
    _unique([n for n, _ in named], "--source")
    topic_of: dict[str, str] = {}
    for n, t in tops:
        if n is None:
            raise ValueError(f"--topic {t!r}: with named sources, name the camera it is for: --topic NAME=TOPIC")
        if n not in dict(named):
            raise ValueError(f"--topic {n}={t}: no source is named {n!r}; sources: {[x for x, _ in named]}")
        topic_of[n] = t
    _unique([n for n, _ in tops], "--topic")
    return {n: (spec, topic_of.get(n)) for n, spec in named}  # type: ignore[misc]


def _unique(names: list[Any], flag: str) -> None:
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{flag}: each camera once; repeated: {dup}")


def main(args: argparse.Namespace) -> int:
    from vpengine.io.video import check_name
    from vpengine.named_inputs import config_for_cameras
    from vpengine.pipeline.run import Pipeline, open_sources, video_paths

    wanted = parse_sources(args.source or ["synthetic"], args.topic or [])
    cameras = [c for c in wanted if c is not None]
    # the cameras are set before the overrides, which may name them (--set heads.seg.cameras=[rear])
    cfg = config_for_cameras(args.config, cameras or None, engine_overrides(args))
    serve = serve_options(args)
    # every output is checked before the engine starts (and before the source opens a camera)
    if args.out_bag:
        from vpengine.io.bag import check_bag_name

        check_bag_name(args.out_bag, args.bag_storage, "--out-bag")
        prepare_out_file(args.out_bag, False, "--out-bag", replaceable=False)
    if args.video:
        check_name(args.video, "--video")  # the name given, before a camera's name goes into it
    videos = video_paths(args.video, cameras if len(cameras) > 1 else None) if args.video else {}
    for path in videos.values():
        prepare_out_file(path, args.exist_ok, "--video")
    if args.out:
        prepare_out_dir(args.out, args.exist_ok)
    with open_sources(wanted, fps=args.fps, strict=args.strict) as sources:
        factories = []
        if args.out_bag:
            from vpengine.io.bag import BagSink

            def bag_sink(heads: dict[str, dict[str, Any]], served: dict[str, list[str]]) -> Any:
                return BagSink(
                    args.out_bag,
                    heads,
                    storage=args.bag_storage,
                    distro=args.bag_distro,
                    depth_color=args.viz,
                    seg_overlay=args.viz,
                    header_for=_input_headers(sources),
                    cameras=served if len(served) > 1 else None,
                )

            factories.append(bag_sink)

        def report(summary: dict[str, Any]) -> None:
            print(format_summary(summary, listed=args.out is not None))
            if args.out:
                print(f"outputs and summary.json in {args.out}")
            for path in videos.values():
                print(f"annotated video in {path}")
            if args.out_bag:
                print(f"outputs recorded to bag {args.out_bag}")
            sys.stdout.flush()  # before a wait in the live view (Note [Serving on])

        pipe = Pipeline(
            cfg,
            sources if cameras else sources[None],
            args.out,
            args.pace,
            args.fps,
            args.max_frames,
            args.save_every,
            args.viz,
            progress=not args.no_progress,
            sink_factories=factories,
            depth_format=args.depth_format,
            video=args.video,
        )
        summary = run_served(pipe, serve, report)
    return exit_status(summary, "run")


#: The exit status of a run that went to its end with frames some model failed on (each counted in the summary)
FRAMES_FAILED = 3


def exit_status(summary: dict[str, Any], command: str) -> int:
    """A finished run's exit status: 130 interrupted; FRAMES_FAILED when a model failed on frames or its worker was
    restarted, said in a last line on stderr, so that a script or a CI job sees it, not only the table; else 0."""
    if summary["interrupted"]:
        return 130
    models = summary["models"]
    failed = ", ".join(f"{n} {m['errors']}" for n, m in models.items() if m.get("errors"))
    restarted = ", ".join(f"{n} {m['restarts']}" for n, m in models.items() if m.get("restarts"))
    said = [f"frames a model failed on: {failed}"] if failed else []
    said += [f"workers restarted: {restarted}"] if restarted else []
    if not said:
        return 0
    print(
        f"vpengine {command}: {'; '.join(said)} (counted in summary.json, the log says why); exit status {FRAMES_FAILED}",
        file=sys.stderr,
    )
    return FRAMES_FAILED


def _input_headers(sources: Mapping[str | None, Source]) -> Callable[[Result, str], Header] | None:
    """The output bag's header of each result: its input message's, exactly, where its camera's source is a bag
    (``BagSource.header_for``), else its capture time and camera; None when no source is a bag (the sink's own)."""
    from vpengine.ros2.messages import Header

    lookups = {c: s.header_for for c, s in sources.items()}
    if not any(lookups.values()):
        return None
    if len(lookups) == 1:
        return next(iter(lookups.values()))

    def header_for(result: Result, name: str) -> Header:
        lookup = lookups.get(result.camera)
        return lookup(result, name) if lookup is not None else Header.from_seconds(result.capture_time, result.camera)

    return header_for
