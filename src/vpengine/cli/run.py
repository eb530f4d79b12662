"""``vpengine run``: a pipeline over a video, an image folder, a camera or the built-in synthetic scene.

Pacing decides what happens when models are slower than the source:

* ``lockstep`` (default for files): the next frame goes in once every head has answered the previous one, with an
  output or, when its rate limit holds the frame back, with none (Note [Answered frames]), so nothing is skipped
  by accident and the run is as fast as the heads that run on each frame allow. Rate limits run on the source's own
  timeline: a video's frames by their position, a folder's at ``--fps`` (default 30), a bag's by their stamps;
* ``realtime`` (default for cameras and the synthetic scene): frames go in at the source's rate like a live camera;
  models take the newest frame and every frame they skip is counted in the summary.

A camera is read on its own thread and the loop takes its newest frame; frames it replaced are counted too (Note
[Live capture] in ``vpengine.io.sources``). Outputs are written on a writer thread (Note [Sink thread] in
``vpengine.io.sinks``). Every output is checked before the engine starts; Ctrl-C ends the run after the frame in
hand and still prints and writes the summary (Note [Ctrl-C]).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import functools
import json
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from vpengine.cli import (
    add_config_argument,
    add_overrides_argument,
    positive_float,
    positive_int,
    prepare_out_dir,
    prepare_out_file,
)
from vpengine.cli.serve import ServeOptions, add_serve_arguments, serve_options, serving

log = logging.getLogger("vpengine.run")

SOURCE_HELP = (
    "an image, a folder or a glob of images ('frames/*.jpg'), a video file, a rosbag2 bag (folder or .mcap/.db3), "
    "camera:N, sample:street or sample:cheetah (shipped with vpengine), or synthetic[:WxH][@FPS][:FRAMES]"
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_config_argument(p)
    p.add_argument("--source", "-s", default="synthetic", help=SOURCE_HELP + " (default: synthetic)")
    p.add_argument("--topic", help="image topic of a bag source (sensor_msgs/Image or CompressedImage)")
    p.add_argument(
        "--strict",
        action="store_true",
        help="stop at a bag's first bad message (default: skip it, log it, list it in the summary)",
    )
    p.add_argument(
        "--out-bag", help="also record every head's outputs to this new rosbag2 bag (ROS 2 message types)"
    )
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
    p.add_argument(
        "--exist-ok", action="store_true", help="write into an --out folder (or over a --video) that exists"
    )
    add_overrides_argument(p, "heads.depth.rate_hz=5")
    p.add_argument(
        "--pace", choices=["lockstep", "realtime"], help="see `vpengine run --help` (default by source)"
    )
    p.add_argument(
        "--fps",
        type=positive_float,
        help="realtime pace in Hz and the rate images are stamped at (default: the source's own rate, else 30; a "
        "camera paces itself unless given)",
    )
    p.add_argument("--max-frames", type=positive_int, help="stop after this many frames")
    p.add_argument(
        "--save-every", type=positive_int, default=1, help="write every Nth output per head (default: all)"
    )
    p.add_argument(
        "--depth-format",
        choices=["png16", "npy"],
        default="png16",
        help="depth files: 16-bit PNG with its scale in depth_scale.jsonl (default; Note [Depth PNG]) or float32 .npy",
    )
    p.add_argument(
        "--viz", action="store_true", help="also write pictures: depth with a colour bar, overlays, boxes"
    )
    p.add_argument(
        "--video",
        help="also write an annotated mp4: the input and every head side by side, one frame per frame",
    )
    p.add_argument("--mode", choices=["process", "thread"], help="override the config's mode")
    p.add_argument("--device", help="override the config's device (cpu, cuda, cuda:N)")
    p.add_argument(
        "--random-weights", action="store_true", help="use random weights (loudly) instead of checkpoints"
    )
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
    sink_factories: Sequence[Callable[[dict[str, dict[str, Any]]], Any]] = (),
    depth_format: str = "png16",
    video: str | Path | None = None,
    folder: bool = True,
    serve: ServeOptions | None = None,
) -> dict[str, Any]:
    """Run ``config`` over ``source``; returns the summary (also written to ``out_dir/summary.json``).

    ``out_dir`` gets every head's outputs (unless ``folder`` is False) and the summary; ``video`` an annotated mp4
    (Note [Annotated frames]). ``sink_factories`` make extra sinks (e.g. a rosbag2 BagSink) from the heads'
    ``head_info``; each gets every result with its input frame and name, like the folder sink. Every sink is made,
    written and closed on one writer thread, not the caller's (Note [Sink thread] in ``vpengine.io.sinks``).
    Ctrl-C ends the run after the frame in hand; the summary then says ``interrupted`` (Note [Ctrl-C]). ``serve``: the
    live view (``vpengine.web``) while it runs, drawing on the recent frames the loop keeps."""
    from tqdm import tqdm

    from vpengine.config import load_config
    from vpengine.engine import Engine
    from vpengine.io.sinks import AnnotatedSink, FolderSink, SinkThread

    # frames of any size go in as they are (Note [Frame grid] in boundary.py): the CLI resizes nothing itself
    cfg = load_config(config, [f"input.color={source.color}"])
    # a camera paces itself: the loop takes its newest frame (Note [Live capture])
    camera = getattr(source, "live", False)
    live = camera or type(source).__name__ == "SyntheticSource"
    pace = pace or ("realtime" if live else "lockstep")
    if pace not in ("realtime", "lockstep"):
        raise ValueError(f"pace must be 'realtime' or 'lockstep', got {pace!r}")
    period = 1.0 / (fps or source.fps or 30.0)
    total = len(source) or None
    if max_frames is not None:
        total = min(total or max_frames, max_frames)

    engine = Engine(cfg)
    t0 = time.monotonic()
    engine.start()
    log.info("engine started in %.1f s", time.monotonic() - t0)
    heads = list(engine.plan.heads)
    try:
        info = {h: engine.head_info(h) for h in heads}
        factories: list[Callable[[], Any]] = []
        if out_dir and folder:
            factories.append(functools.partial(FolderSink, out_dir, info, viz, save_every, depth_format))
        if video:
            rate = fps or source.fps or 30.0
            factories.append(functools.partial(AnnotatedSink, info, video=video, fps=rate))
        factories += [functools.partial(make, info) for make in sink_factories]
        # Note [Sink thread]: lockstep waits for the writer (nothing lost), a live source never does (counted)
        writer = SinkThread(factories, max_pending=4 * max(len(heads), 1), block=pace == "lockstep")
    except BaseException:
        engine.stop()
        raise
    recent: collections.OrderedDict[int, tuple[np.ndarray, str]] = collections.OrderedDict()
    latencies: dict[str, list[float]] = {h: [] for h in heads}
    received = dict.fromkeys(heads, 0)
    bar = tqdm(total=total, unit="frame", disable=not progress, mininterval=0.5, dynamic_ncols=True)

    def handle(results: list[Any]) -> None:
        for r in results:
            received[r.head] += 1
            latencies[r.head].append(r.latency)
            frame, name = recent.get(r.frame_id, (None, str(r.frame_id)))
            if factories:
                writer.put(r, frame, name)

    submitted = 0
    interrupted = False
    t_start = time.monotonic()
    next_t = t_start
    view = contextlib.ExitStack()
    try:
        view.enter_context(serving(serve, engine, lambda fid: recent.get(fid, (None,))[0], cfg.input.color))
        with _ctrl_c() as stop:
            if pace == "realtime":
                engine.results(0)  # start the result stream before the first frame
            for frame in source:
                if (max_frames is not None and submitted >= max_frames) or stop.is_set():
                    break
                if pace == "realtime" and (fps is not None or not camera):
                    now = time.monotonic()
                    if next_t > now:
                        handle(engine.results(timeout=next_t - now))
                        while (now := time.monotonic()) < next_t:
                            handle(engine.results(timeout=next_t - now))
                    next_t = max(next_t + period, time.monotonic() - period)
                stamp = frame.timestamp
                if stamp is None and pace == "lockstep":  # a file without stamps: its own timeline at the pace
                    stamp = submitted * period
                fid = engine.submit(frame.image, timestamp=stamp)
                recent[fid] = (frame.image, frame.name or f"{fid:06d}")
                if len(recent) > 64:
                    recent.popitem(last=False)
                submitted += 1
                if pace == "lockstep":
                    try:
                        handle(list(engine.wait(fid, timeout=60.0).values()))
                    except TimeoutError as e:
                        log.warning("%s", e)
                else:
                    handle(engine.results(0))
                bar.update(1)
                if submitted % 10 == 0:
                    st = engine.stats()["models"]
                    bar.set_postfix_str(
                        " ".join(f"{n}={m['achieved_hz']:.1f}Hz" for n, m in st.items()), refresh=False
                    )
            if pace == "realtime":  # let in-flight frames finish
                deadline = time.monotonic() + 2.0
                while time.monotonic() < deadline and not stop.is_set():
                    res = engine.results(timeout=0.2)
                    handle(res)
                    if not res:
                        break
            interrupted = stop.is_set()
        wall = time.monotonic() - t_start
        stats = engine.stats()
    finally:
        bar.close()
        view.close()
        engine.stop()
        writer.close()  # writes what is queued; raises a sink's error

    models = {}
    for name, m in stats["models"].items():
        models[name] = {
            "target_hz": m["target_hz"],
            "achieved_hz": m["runs"] / wall if wall > 0 else 0.0,
            "runs": m["runs"],
            "skipped": m["skipped"],
            "dropped": m["dropped"],
            "errors": m["errors"],
            "restarts": m["restarts"],
            "latency_ms": {"p50": m["latency_ms"]["p50"], "p99": m["latency_ms"]["p99"]},
        }
        if name in latencies:
            models[name]["e2e_latency_ms"] = _percentiles(latencies[name])
            models[name]["results_received"] = received[name]
            models[name]["results_missed"] = stats["results"][name]["missed"]
            models[name]["results_unwritten"] = writer.unwritten[name]
    summary = {
        "config": cfg.name,
        "source": str(getattr(source, "path", type(source).__name__)),
        "pace": pace,
        "frames_submitted": submitted,
        "source_missed": getattr(source, "missed", 0),
        "inputs_skipped": getattr(source, "skipped", []),
        "inputs_partial": getattr(source, "partial", []),
        "interrupted": interrupted,
        "wall_s": wall,
        "input_hz": submitted / wall if wall > 0 else 0.0,
        "mode": cfg.mode,
        "device": cfg.device,
        "models": models,
        "warnings": engine.plan.warnings,
    }
    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default))
    return summary


@contextmanager
def _ctrl_c() -> Iterator[threading.Event]:
    """Note [Ctrl-C]: the first Ctrl-C (SIGINT) during a run sets the event; the frame loop ends after the frame in
    hand, and the engine is stopped, queued outputs are written and the summary is made as after the last frame.
    It is not raised where it lands: a KeyboardInterrupt inside ``submit`` or ``wait`` could leave the engine's
    locks held and hang the stop that follows. A second Ctrl-C raises KeyboardInterrupt at once (a source that
    delivers no frame, a head that never answers). Only the main thread can take signals; elsewhere the event is
    never set."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def on_sigint(signum: int, frame: Any) -> None:
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
        print("\nstopping after this frame (Ctrl-C again to abort)", file=sys.stderr, flush=True)

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)


def _json_default(o: Any) -> Any:
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return str(o)


def format_summary(s: dict[str, Any]) -> str:
    missed = f"; camera frames a newer one replaced: {s['source_missed']}" if s.get("source_missed") else ""
    stopped = "interrupted after " if s.get("interrupted") else ""
    lines = [
        f"{stopped}{s['frames_submitted']} frames in {s['wall_s']:.1f} s ({s['input_hz']:.1f} Hz in, {s['pace']}, "
        f"{s['mode']} mode on {s['device']}{missed})",
        f"{'model':14s} {'target':>7s} {'achieved':>9s} {'runs':>6s} {'skipped':>8s} {'dropped':>8s} "
        f"{'errors':>6s} {'p50 ms':>8s} {'p99 ms':>8s}",
    ]
    for name, m in s["models"].items():
        lat = m.get("e2e_latency_ms") or m["latency_ms"]

        def f(v: Any) -> str:
            return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.1f}"

        tgt = "max" if m["target_hz"] is None else f"{m['target_hz']:g}"
        lines.append(
            f"{name:14s} {tgt:>7s} {m['achieved_hz']:9.1f} {m['runs']:6d} {m['skipped']:8d} "
            f"{m['dropped']:8d} {m['errors']:6d} {f(lat['p50']):>8s} {f(lat['p99']):>8s}"
        )
    lines.append("(latency: submit -> result for heads; model time for the foundation model)")
    if s.get("inputs_skipped"):
        lines.append(f"images skipped as unreadable: {len(s['inputs_skipped'])} (listed in summary.json)")
    if s.get("inputs_partial"):
        lines.append(
            f"images truncated, decoded partially: {len(s['inputs_partial'])} (listed in summary.json)"
        )
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


def main(args: argparse.Namespace) -> int:
    from vpengine.config import load_config
    from vpengine.io.sources import open_source

    cfg = load_config(args.config, engine_overrides(args))
    serve = serve_options(args)
    # every output is checked before the engine starts (and before the source opens a camera)
    if args.out_bag:
        prepare_out_file(args.out_bag, False, "--out-bag", replaceable=False)
    if args.video:
        prepare_out_file(args.video, args.exist_ok, "--video")
    if args.out:
        prepare_out_dir(args.out, args.exist_ok)
    with open_source(args.source, topic=args.topic, fps=args.fps, strict=args.strict) as source:
        factories = []
        if args.out_bag:
            from vpengine.io.bag import BagSink

            def bag_sink(heads: dict[str, dict[str, Any]]) -> Any:
                return BagSink(
                    args.out_bag,
                    heads,
                    storage=args.bag_storage,
                    distro=args.bag_distro,
                    depth_color=args.viz,
                    seg_overlay=args.viz,
                    header_for=getattr(source, "header_for", None),  # bag sources keep exact input headers
                )

            factories.append(bag_sink)
        summary = run_pipeline(
            cfg,
            source,
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
        )
    print(format_summary(summary))
    if args.out:
        print(f"outputs and summary.json in {args.out}")
    if args.video:
        print(f"annotated video in {args.video}")
    if args.out_bag:
        print(f"outputs recorded to bag {args.out_bag}")
    return 130 if summary["interrupted"] else 0
