"""``vpengine run``: a pipeline over a video, an image folder, a camera or the built-in synthetic scene.

Pacing decides what happens when models are slower than the source:

* ``lockstep`` (default for files): the next frame goes in once every head has answered the previous one, with an
  output or, when its rate limit holds the frame back, with none (Note [Answered frames]), so nothing is skipped
  by accident and the run is as fast as the heads that run on each frame allow. Rate limits run on the source's own
  timeline: a video's frames by their position, a folder's at ``--fps`` (default 30), a bag's by their stamps;
* ``realtime`` (default for cameras and the synthetic scene): frames go in at the source's rate like a live camera;
  models take the newest frame and every frame they skip is counted in the summary.

Several cameras: ``--source NAME=SPEC`` for each; every source feeds its camera on its own timeline (Note [Several
sources] in ``vpengine.cli.pacing``), outputs go to ``DIR/<camera>/<head>/``, and the summary counts per camera as well as per model.

A camera is read on its own thread and the loop takes its newest frame; frames it replaced are counted too (Note
[Live capture] in ``vpengine.io.sources``). Outputs are written on a writer thread (Note [Sink thread] in
``vpengine.io.sinks``). Every output is checked before the engine starts; Ctrl-C ends the run after the frame in
hand and still prints and writes the summary (Note [Ctrl-C] in ``vpengine.cli.pacing``). With ``--serve``, the live
view of a run that ends on its own stays up after the summary until Ctrl-C (Note [Serving on] in ``vpengine.cli.serve``).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import functools
import json
import logging
import math
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from vpengine.arguments import add_config_argument, add_overrides_argument, positive_float, positive_int
from vpengine.cli import prepare_out_dir, prepare_out_file
from vpengine.cli.pacing import Feed, ctrl_c, lockstep, realtime
from vpengine.cli.serve import ServeOptions, add_serve_arguments, keep_serving, serve_options, serving
from vpengine.redact import redact

log = logging.getLogger("vpengine.run")

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
        "source, or repeated with one bag source: a camera per topic",
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
        help="also write an annotated mp4: the input and every head side by side, one frame per frame",
    )
    p.add_argument("--mode", choices=["process", "thread"], help="override the config's mode")
    p.add_argument("--device", help="override the config's device (cpu, cuda, cuda:N)")
    p.add_argument("--random-weights", action="store_true", help="use random weights (loudly) instead of checkpoints")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_serve_arguments(p)


def _percentiles(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p99": None, "mean": None}
    a = np.asarray(values) * 1e3
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)), "mean": float(a.mean())}


def run_pipeline(
    config: Any,
    source: Any,
    out_dir: str | Path | None = None,
    pace: str | None = None,
    fps: float | None = None,
    max_frames: int | None = None,
    save_every: int = 1,
    viz: bool = False,
    progress: bool = True,
    sink_factories: Sequence[Callable[[dict[str, dict[str, Any]], dict[str, list[str]]], Any]] = (),
    depth_format: str = "png16",
    video: str | Path | None = None,
    folder: bool = True,
    serve: ServeOptions | None = None,
    ended: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Run ``config`` over ``source``; returns the summary (also written to ``out_dir/summary.json``).

    ``source``: one source, or camera name -> source for several cameras (Note [Several sources]); the engine's
    cameras are then those names (``config_for_cameras``). ``out_dir`` gets every head's outputs (unless ``folder``
    is False; ``out_dir/<camera>/`` each with several cameras) and the summary; ``video`` an annotated mp4 (Note
    [Annotated frames]; one per camera, :func:`video_paths`). ``sink_factories`` make extra sinks (e.g. a rosbag2
    BagSink) from the heads' ``head_info`` and the heads each camera has (camera -> head names); each gets every
    result with its input frame and name, like the folder sink. Every sink is made, written and closed on one
    writer thread, not the caller's (Note [Sink thread] in ``vpengine.io.sinks``). ``max_frames`` counts per
    source. Ctrl-C ends the run after the frame in hand; the summary then says ``interrupted`` (Note [Ctrl-C]).
    ``serve``: the live view (``vpengine.web``) while it runs, drawing on the recent frames the loop keeps.
    ``ended``: called with the summary once the run is over (outputs and summary.json written), for the caller to
    report it; with ``serve``, the view of a run that ended on its own then stays up, on the idle engine, until
    Ctrl-C or SIGTERM (Note [Serving on] in ``vpengine.cli.serve``)."""
    from tqdm import tqdm

    from vpengine.config import config_for_cameras
    from vpengine.engine import Engine
    from vpengine.io.sinks import AnnotatedSink, FolderSink, SinkThread, per_camera

    sources: dict[str | None, Any] = dict(source) if isinstance(source, Mapping) else {None: source}
    names = [c for c in sources if c is not None] or None
    colors = {s.color for s in sources.values()}
    if len(colors) != 1:
        raise ValueError(f"the sources deliver frames in different channel orders ({sorted(colors)})")
    # frames of any size go in as they are (Note [Frame grid] in boundary.py): the CLI resizes nothing itself
    cfg = config_for_cameras(config, names, [f"input.color={colors.pop()}"])
    pace = pace or ("realtime" if any(_live(s) for s in sources.values()) else "lockstep")
    if pace not in ("realtime", "lockstep"):
        raise ValueError(f"pace must be 'realtime' or 'lockstep', got {pace!r}")
    lengths = [min(len(s) or max_frames or 0, max_frames or len(s)) for s in sources.values()]
    total = sum(lengths) if all(lengths) else None  # None: a source of unknown length

    engine = Engine(cfg)
    t0 = time.monotonic()
    engine.start()
    log.info("engine started in %.1f s", time.monotonic() - t0)
    heads = list(engine.plan.heads)
    # camera -> the heads that serve it (a head may serve some cameras only)
    served = {c: [h for h in heads if c in cfg.model_cameras(h)] for c in engine.cameras}
    several = len(served) > 1
    try:
        info = {h: engine.head_info(h) for h in heads}
        factories: list[Callable[[], Any]] = []
        if out_dir and folder:
            out = Path(out_dir)

            def folders(camera: str | None, infos: dict[str, dict[str, Any]]) -> Any:
                return FolderSink(out / (camera or ""), infos, viz, save_every, depth_format)

            factories.append(functools.partial(per_camera, served, info, folders))
        if video:
            paths = video_paths(video, list(served) if several else None)

            def videos(camera: str | None, infos: dict[str, dict[str, Any]]) -> Any:
                s = sources[camera] if camera is not None else next(iter(sources.values()))
                return AnnotatedSink(infos, video=paths[camera], fps=fps or s.fps or 30.0)

            factories.append(functools.partial(per_camera, served, info, videos))
        factories += [functools.partial(make, info, served) for make in sink_factories]
        # Note [Sink thread]: lockstep waits for the writer (nothing lost), a live source never does (counted)
        writer = SinkThread(factories, max_pending=4 * max(len(heads), 1) * len(served), block=pace == "lockstep")
    except BaseException:
        engine.stop()
        raise
    feeds = [
        Feed(camera, s, 1.0 / (fps or s.fps or 30.0), fps is None and getattr(s, "live", False), iter(s))
        for camera, s in sources.items()
    ]
    # frame id -> (frame, its name); fed and read under one lock: a result may come back before submit returns
    recent: collections.OrderedDict[int, tuple[np.ndarray, str]] = collections.OrderedDict()
    kept = 64 * len(feeds)
    lock = threading.Lock()
    latencies: dict[tuple[str, str], list[float]] = collections.defaultdict(list)
    received: collections.Counter[tuple[str, str]] = collections.Counter()
    unwritten: collections.Counter[tuple[str, str]] = collections.Counter()
    bar = tqdm(total=total, unit="frame", disable=not progress, mininterval=0.5, dynamic_ncols=True)

    def handle(results: Iterable[Any]) -> None:
        for r in results:
            key = (r.camera, r.head)
            received[key] += 1
            latencies[key].append(r.latency)
            with lock:
                frame, name = recent.get(r.frame_id, (None, str(r.frame_id)))
            if factories and not writer.put(r, frame, name):
                unwritten[key] += 1

    def submit(feed: Feed, frame: Any, stamp: float | None) -> int:
        with lock:
            fid = engine.submit(frame.image, timestamp=stamp, camera=feed.camera)
            recent[fid] = (frame.image, frame.name or f"{fid:06d}")
            if len(recent) > kept:
                recent.popitem(last=False)
        feed.submitted += 1
        return fid

    def progressed(done: int) -> None:
        if done > bar.n:
            before, after = bar.n // 10, done // 10
            bar.update(done - bar.n)
            if after > before:
                st = engine.stats()["models"]
                bar.set_postfix_str(" ".join(f"{n}={m['achieved_hz']:.1f}Hz" for n, m in st.items()), refresh=False)

    interrupted = False
    t_start = time.monotonic()
    live = contextlib.ExitStack()  # the engine, then its view: up until the run ends (Note [Serving on])
    live.callback(engine.stop)
    try:
        try:
            server = live.enter_context(
                serving(serve, engine, lambda fid: recent.get(fid, (None,))[0], cfg.input.color)
            )
            with ctrl_c() as stop:
                if pace == "lockstep":
                    lockstep(feeds, max_frames, stop, submit, engine, handle, progressed)
                else:
                    engine.results(0)  # start the result stream before the first frame
                    realtime(feeds, max_frames, stop, submit, engine, handle, progressed)
                    deadline = time.monotonic() + 2.0  # let in-flight frames finish
                    while time.monotonic() < deadline and not stop.is_set():
                        res = engine.results(timeout=0.2)
                        handle(res)
                        if not res:
                            break
                interrupted = stop.is_set()
            wall = time.monotonic() - t_start
            stats = engine.stats()
        finally:
            for f in feeds:
                close = getattr(f.frames, "close", None)  # a generator's clean-up (a camera's reader thread)
                if close is not None:
                    with contextlib.suppress(ValueError):  # still running in a feed that did not end in time
                        close()
            bar.close()
            writer.close()  # writes what is queued; raises a sink's error

        def model_entry(m: dict[str, Any], results: Mapping[str, Any] | None = None) -> dict[str, Any]:
            return {
                "target_hz": m["target_hz"],
                "achieved_hz": m["runs"] / wall if wall > 0 else 0.0,
                "runs": m["runs"],
                "skipped": m["skipped"],
                "dropped": m["dropped"],
                "errors": m["errors"],
                "restarts": m["restarts"],
                "latency_ms": {"p50": m["latency_ms"]["p50"], "p99": m["latency_ms"]["p99"]},
                **(results or {}),
            }

        def head_results(cams: list[str], head: str) -> dict[str, Any]:
            return {
                "e2e_latency_ms": _percentiles([x for c in cams for x in latencies[(c, head)]]),
                "results_received": sum(received[(c, head)] for c in cams),
            }

        models = {}
        for name, m in stats["models"].items():
            extra = None
            if name in heads:
                extra = {
                    **head_results(list(served), name),
                    "results_missed": stats["results"][name]["missed"],
                    "results_unwritten": writer.unwritten[name],
                }
            models[name] = model_entry(m, extra)
        submitted = sum(f.submitted for f in feeds)
        summary = {
            "config": cfg.name,
            "source": ", ".join(_describe(s) if c is None else f"{c}={_describe(s)}" for c, s in sources.items()),
            "pace": pace,
            "frames_submitted": submitted,
            "source_missed": sum(getattr(s, "missed", 0) for s in sources.values()),
            "inputs_skipped": [x for s in sources.values() for x in getattr(s, "skipped", [])],
            "inputs_partial": [x for s in sources.values() for x in getattr(s, "partial", [])],
            "interrupted": interrupted,
            "wall_s": wall,
            "input_hz": submitted / wall if wall > 0 else 0.0,
            "mode": cfg.mode,
            "device": cfg.device,
            "models": models,
            "warnings": engine.plan.warnings,
        }
        if several:  # each camera's frames and models, from stats()["cameras"] (Note [Cameras] in runtime/worker.py)
            by_camera = {f.camera: f for f in feeds}
            summary["cameras"] = {
                c: {
                    "source": _describe(by_camera[c].source),
                    "frames_submitted": by_camera[c].submitted,
                    "source_missed": getattr(by_camera[c].source, "missed", 0),
                    "models": {
                        name: {
                            **model_entry(
                                m,
                                {**head_results([c], name), "results_unwritten": unwritten[(c, name)]}
                                if name in heads
                                else None,
                            ),
                            "late": m.get("late", 0),
                            "deferred": m.get("deferred", 0),
                        }
                        for name, m in stats["cameras"].get(c, {}).items()
                    },
                }
                for c in served
            }
        if out_dir is not None:
            Path(out_dir).mkdir(parents=True, exist_ok=True)
            (Path(out_dir) / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default))
        if ended is not None:
            ended(summary)
            if serve is not None and not interrupted:
                keep_serving(serve, server)
    finally:
        live.close()
    return summary


def _live(source: Any) -> bool:
    """A source that delivers frames at its own rate, like a camera: paced in realtime by default."""
    return bool(getattr(source, "live", False)) or type(source).__name__ == "SyntheticSource"


def _describe(source: Any) -> str:
    """How the summary names ``source``: its path or URL without a password (Note [Redacting] in vpengine/redact.py)."""
    return redact(str(getattr(source, "path", type(source).__name__)))


def video_paths(video: str | Path, cameras: Sequence[str] | None) -> dict[str | None, Path]:
    """Where ``--video PATH`` writes: PATH itself for one camera (key None), ``<stem>_<camera><suffix>`` beside it
    for each of several cameras."""
    p = Path(video)
    if not cameras:
        return {None: p}
    return {c: p.with_name(f"{p.stem}_{c}{p.suffix}") for c in cameras}


def _json_default(o: Any) -> Any:
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return str(o)


def format_summary(s: dict[str, Any]) -> str:
    missed = f"; camera frames a newer one replaced: {s['source_missed']}" if s.get("source_missed") else ""
    stopped = "interrupted after " if s.get("interrupted") else ""
    cameras = s.get("cameras") or {}
    each = ", ".join(f"{c} {x['frames_submitted']}" for c, x in cameras.items())
    each = f" ({each})" if each else ""
    w = max([14] + [len(f"{n}@{c}") for c, x in cameras.items() for n in x["models"]])
    lines = [
        f"{stopped}{s['frames_submitted']} frames{each} in {s['wall_s']:.1f} s ({s['input_hz']:.1f} Hz in, "
        f"{s['pace']}, {s['mode']} mode on {s['device']}{missed})",
        f"{'model':{w}s} {'target':>7s} {'achieved':>9s} {'runs':>6s} {'skipped':>8s} {'dropped':>8s} "
        f"{'errors':>6s} {'p50 ms':>8s} {'p99 ms':>8s}",
    ]

    def f(v: Any) -> str:
        return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.1f}"

    def row(name: str, m: dict[str, Any]) -> str:
        lat = m.get("e2e_latency_ms") or m["latency_ms"]
        tgt = "max" if m["target_hz"] is None else f"{m['target_hz']:g}"
        return (
            f"{name:{w}s} {tgt:>7s} {m['achieved_hz']:9.1f} {m['runs']:6d} {m['skipped']:8d} "
            f"{m['dropped']:8d} {m['errors']:6d} {f(lat['p50']):>8s} {f(lat['p99']):>8s}"
        )

    lines += [row(name, m) for name, m in s["models"].items()]
    for camera, x in cameras.items():  # each camera's share, named model@camera as rate commands name it
        lines += [row(f"{name}@{camera}", m) for name, m in x["models"].items()]
    lines.append("(latency: submit -> result for heads; model time for the foundation model)")
    if s.get("inputs_skipped"):
        lines.append(f"images skipped as unreadable: {len(s['inputs_skipped'])} (listed in summary.json)")
    if s.get("inputs_partial"):
        lines.append(f"images truncated, decoded partially: {len(s['inputs_partial'])} (listed in summary.json)")
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
    unnamed source of a one-camera run (of several unnamed ones, the last, as an option given twice).
    ``NAME=SPEC`` names a source's camera (a path that exists is never read as a name); ``--topic NAME=TOPIC`` gives camera NAME's bag topic, and with one unnamed bag source, several of
    them make one camera of each topic. ValueError naming what does not fit."""
    from vpengine.config import split_camera

    named = [(None, s) if Path(s).exists() else split_camera(s) for s in sources]
    if not any(n for n, _ in named):
        named = named[-1:]  # unnamed, a later --source replaces an earlier one, as any option's value
    tops = [split_camera(t) for t in topics]
    if not any(n for n, _ in tops):
        tops = tops[-1:]
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


@contextmanager
def open_sources(
    wanted: Mapping[str | None, tuple[str, str | None]], fps: float | None = None, strict: bool = False
) -> Iterator[dict[str | None, Any]]:
    """Every source of :func:`parse_sources`, open for the block (closed after it, also when one fails to open)."""
    from vpengine.io.sources import open_source

    with contextlib.ExitStack() as stack:
        yield {
            camera: stack.enter_context(open_source(spec, topic=topic, fps=fps, strict=strict))
            for camera, (spec, topic) in wanted.items()
        }


def main(args: argparse.Namespace) -> int:
    from vpengine.config import config_for_cameras

    wanted = parse_sources(args.source or ["synthetic"], args.topic or [])
    cameras = [c for c in wanted if c is not None]
    # the cameras are set before the overrides, which may name them (--set heads.seg.cameras=[rear])
    cfg = config_for_cameras(args.config, cameras or None, engine_overrides(args))
    serve = serve_options(args)
    # every output is checked before the engine starts (and before the source opens a camera)
    if args.out_bag:
        prepare_out_file(args.out_bag, False, "--out-bag", replaceable=False)
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
            print(format_summary(summary))
            if args.out:
                print(f"outputs and summary.json in {args.out}")
            for path in videos.values():
                print(f"annotated video in {path}")
            if args.out_bag:
                print(f"outputs recorded to bag {args.out_bag}")
            sys.stdout.flush()  # before a wait in the live view (Note [Serving on])

        summary = run_pipeline(
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
            serve=serve,
            ended=report,
        )
    return 130 if summary["interrupted"] else 0


def _input_headers(sources: Mapping[str | None, Any]) -> Callable[[Any, str], Any] | None:
    """The output bag's header of each result: its input message's, exactly, where its camera's source is a bag
    (``BagSource.header_for``), else its capture time and camera; None when no source is a bag (the sink's own)."""
    from vpengine.ros2.core import Header

    lookups = {c: getattr(s, "header_for", None) for c, s in sources.items()}
    if not any(lookups.values()):
        return None
    if len(lookups) == 1:
        return next(iter(lookups.values()))

    def header_for(result: Any, name: str) -> Any:
        lookup = lookups.get(result.camera)
        return lookup(result, name) if lookup is not None else Header.from_seconds(result.capture_time, result.camera)

    return header_for
