"""A pipeline: frames from sources into an engine, its results out to sinks, and a summary of the run.

Pacing decides what happens when models are slower than the source:

* ``lockstep`` (default for files): the next frame goes in once every head has answered the previous one, with an
  output or, when its rate limit holds the frame back, with none (Note [Answered frames]), so nothing is skipped
  by accident and the run is as fast as the heads that run on each frame allow. Rate limits run on the source's own
  timeline: a video's frames by their position, a folder's at ``fps`` (default 30), a bag's by their stamps;
* ``realtime`` (default for cameras and the synthetic scene, ``Source.pace``): frames go in at the source's rate
  like a live camera; models take the newest frame and every frame they skip is counted in the summary.

Several cameras: a source for each, by camera name; every source feeds its camera on its own timeline (Note
[Several sources] in ``vpengine.pipeline.pacing``), outputs go to ``DIR/<camera>/<head>/``, and the summary counts
per camera as well as per model.

A camera is read on its own thread and the loop takes its newest frame; frames it replaced are counted too (Note
[Live capture] in ``vpengine.io.sources``). In lockstep, files are read a few frames ahead on a thread of their own
(Note [Read ahead] in ``vpengine.io.readahead``) and answered on another (Note [Answering thread] in
``vpengine.pipeline.pacing``). Outputs are written on a writer thread (Note [Sink thread] in
``vpengine.io.sinks``). Ctrl-C ends the run after the frame in hand and still makes and writes the summary (Note
[Ctrl-C] in ``vpengine.pipeline.pacing``).

::

    with Pipeline(config, source, out_dir) as pipe:   # the engine started, the sinks made
        ...                                           # e.g. a live view of pipe.engine drawing on pipe.frames
        summary = pipe.run()                          # frames in until the source ends; sinks closed
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from vpengine.config import EngineConfig
from vpengine.engine import Engine
from vpengine.engine.results import Result
from vpengine.io.base import Frame, Source
from vpengine.io.readahead import ReadAhead
from vpengine.io.sinks import AnnotatedSink, FolderSink, Sink, SinkThread, per_camera
from vpengine.named_inputs import config_for_cameras
from vpengine.pipeline.pacing import Feed, FrameLoop, ctrl_c, lockstep, pipelined, realtime
from vpengine.pipeline.summary import Tally, summarize, write_summary
from vpengine.recent_frames import RecentFrames

log = logging.getLogger("vpengine.run")

#: Makes an extra sink from the heads' ``head_info`` and the heads each camera has (camera -> head names).
SinkFactory = Callable[[dict[str, dict[str, Any]], dict[str, list[str]]], Sink]
#: Input frames kept per source for the sinks and pictures that draw on them (Note [Pictures and frames]).
FRAMES_KEPT = 64
#: Frames a lockstep run reads ahead of the loop, per source (Note [Read ahead]): enough to cover a slow decode
#: (a keyframe) while the loop writes a round of frames and waits for the oldest in flight.
READ_AHEAD = 4
#: Seconds a realtime run waits at its end for the frames in flight (Note [The frames in flight at the end]): a
#: minute of a model's frames, at seconds a frame, before it gives up on a head and says so
END_WAIT_S = 60.0


class Pipeline:
    """``config`` over ``source``: a context manager that starts the engine and makes the sinks, and :meth:`run`.

    ``source``: one source, or camera name -> source for several cameras (Note [Several sources]); the engine's
    cameras are then those names (``config_for_cameras``). ``out_dir`` gets every head's outputs (unless ``folder``
    is False; ``out_dir/<camera>/`` each with several cameras) and the summary; ``video`` an annotated mp4 (Note
    [Annotated frames]; one per camera, :func:`video_paths`). ``sink_factories`` make extra sinks (e.g. a rosbag2
    BagSink); each gets every result with its input frame and name, like the folder sink. Every sink is made,
    written and closed on one writer thread, not the caller's (Note [Sink thread] in ``vpengine.io.sinks``).
    ``max_frames`` counts per source. ``frames`` keeps the recent input frames by frame id, for a live view."""

    def __init__(
        self,
        config: EngineConfig | str | Path,
        source: Source | Mapping[str | None, Source],
        out_dir: str | Path | None = None,
        pace: str | None = None,
        fps: float | None = None,
        max_frames: int | None = None,
        save_every: int = 1,
        viz: bool = False,
        progress: bool = True,
        sink_factories: Sequence[SinkFactory] = (),
        depth_format: str = "png16",
        video: str | Path | None = None,
        folder: bool = True,
    ) -> None:
        self.sources: dict[str | None, Source] = dict(source) if isinstance(source, Mapping) else {None: source}
        names = [c for c in self.sources if c is not None] or None
        colors = {s.color for s in self.sources.values()}
        if len(colors) != 1:
            raise ValueError(f"the sources deliver frames in different channel orders ({sorted(colors)})")
        # frames of any size go in as they are (Note [Frame grid] in engine/boundary.py): the pipeline resizes nothing itself
        # the sources deliver uint8 frames in their own channel order: the config's input says how the API's callers
        # hand theirs in, not how a file or camera does
        self.config = config_for_cameras(config, names, [f"input.color={colors.pop()}", "input.dtype=uint8"])
        self.pace = pace or ("realtime" if any(s.pace == "realtime" for s in self.sources.values()) else "lockstep")
        if self.pace not in ("realtime", "lockstep"):
            raise ValueError(f"pace must be 'realtime' or 'lockstep', got {self.pace!r}")
        self.in_flight = 1  # rounds of frames submitted and not yet answered, at most (Note [Frames in flight])
        if self.pace == "lockstep":
            self.config, self.in_flight = pipelined(self.config)
        self.out_dir, self.fps, self.max_frames, self.progress = out_dir, fps, max_frames, progress
        self._sinks = (save_every, viz, list(sink_factories), depth_format, video, folder)
        self.frames: RecentFrames[str] = RecentFrames(FRAMES_KEPT * len(self.sources))
        # frame ids are chosen here and each frame booked before its submit: a result may come back before submit
        # returns, and must find its frame; the feeds' submits run at once, each camera filling its own slot (Note
        # [Frames of several cameras at once] in engine/core.py)
        self._fids = itertools.count()  # next() is atomic: the feeds' threads share it
        self.tally = Tally()
        self.feeds: list[Feed] = []

    # ---------------------------------------------------------------------------------------- start, stop
    def __enter__(self) -> Pipeline:
        self.engine = Engine(self.config)
        t0 = time.monotonic()
        self.engine.start()
        log.info("engine started in %.1f s", time.monotonic() - t0)
        try:
            self.heads = list(self.engine.plan.heads)
            # camera -> the heads that serve it (a head may serve some cameras only)
            self.served = {c: [h for h in self.heads if c in self.engine.lanes.served(h)] for c in self.engine.cameras}
            self.writer = self._make_writer()
        except BaseException:
            self.engine.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.writer.close()  # done already after run(); writes what is queued; raises a sink's error
        finally:
            self.engine.stop()

    def _make_writer(self) -> SinkThread:
        save_every, viz, sink_factories, depth_format, video, folder = self._sinks
        info = {h: self.engine.head_info(h) for h in self.heads}
        factories: list[Callable[[], Sink]] = []
        if self.out_dir and folder:
            out = Path(self.out_dir)

            def folders(camera: str | None, infos: dict[str, dict[str, Any]]) -> Sink:
                return FolderSink(out / (camera or ""), infos, viz, save_every, depth_format)

            factories.append(functools.partial(per_camera, self.served, info, folders))
        if video:
            paths = video_paths(video, list(self.served) if len(self.served) > 1 else None)

            def videos(camera: str | None, infos: dict[str, dict[str, Any]]) -> Sink:
                s = self.sources[camera] if camera is not None else next(iter(self.sources.values()))
                return AnnotatedSink(infos, video=paths[camera], fps=self.fps or s.fps or 30.0)

            factories.append(functools.partial(per_camera, self.served, info, videos))
        factories += [functools.partial(make, info, self.served) for make in sink_factories]
        self._writes = bool(factories)
        # Note [Sink thread]: lockstep waits for the writer (nothing lost), a live source never does (counted)
        pending = 4 * max(len(self.heads), 1) * len(self.served)
        return SinkThread(factories, max_pending=pending, block=self.pace == "lockstep")

    # ---------------------------------------------------------------------------------------------- run
    def run(self) -> dict[str, Any]:
        """Feed every frame (up to ``max_frames`` a source) or until Ctrl-C, write the outputs, and return the
        summary (also written to ``out_dir/summary.json``); the summary says ``interrupted`` after a Ctrl-C
        (Note [Ctrl-C])."""
        from tqdm import tqdm

        lengths = [min(len(s) or self.max_frames or 0, self.max_frames or len(s)) for s in self.sources.values()]
        total = sum(lengths) if all(lengths) else None  # None: a source of unknown length
        self._bar = tqdm(total=total, unit="frame", disable=not self.progress, mininterval=0.5, dynamic_ncols=True)
        t_start = time.monotonic()
        try:
            self.feeds = []
            for camera, s in self.sources.items():
                frames = self._frames(camera, s)
                self.feeds.append(
                    Feed(camera, s, 1.0 / (self.fps or s.fps or 30.0), self.fps is None and s.live, frames)
                )
            with ctrl_c() as stop:
                interrupted = self._feed(stop)
            wall = time.monotonic() - t_start
            stats = self.engine.stats()
        finally:
            self._end_feeds()
        summary = summarize(self, interrupted, wall, stats)
        if self.out_dir is not None:
            write_summary(self.out_dir, summary)
        return summary

    def _feed(self, stop: threading.Event) -> bool:
        """Every frame in, and its results handled; whether a stop (Ctrl-C) cut the frames short."""
        loop = FrameLoop(
            self.feeds, self.max_frames, stop, self._submit, self.engine, self._handle, self._progressed, self.in_flight
        )
        if self.pace == "lockstep":
            lockstep(loop)
            return stop.is_set()
        self.engine.results(0)  # start the result stream before the first frame
        realtime(loop)
        interrupted = stop.is_set()  # a Ctrl-C in the wait below ends the wait, not the frames: all went in
        self._answer_the_last(stop)
        return interrupted

    def _answer_the_last(self, stop: threading.Event) -> None:
        """Note [The frames in flight at the end]
        ~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~
        A realtime run ends once every head has answered each camera's last frame (ran it, or skipped it as
        newest-wins or a rate limit would): every earlier frame is answered by then too, and the stream holds every
        output. A quiet poll of the stream is no sign of the end: a model slower than the poll was left behind, its
        frames in no count. The wait is bounded (END_WAIT_S; then a warning names the heads still working, and their
        frames in flight are in no count), and a Ctrl-C ends it within half a second."""
        deadline = time.monotonic() + END_WAIT_S
        for feed in self.feeds:
            while feed.last_fid is not None and not stop.is_set():
                try:
                    self.engine.wait(feed.last_fid, timeout=0.5, copy=False)
                    break
                except ValueError:  # so long ago that the engine no longer keeps it: answered long since
                    break
                except TimeoutError as e:
                    self._handle(self.engine.results(0))  # keep the stream drained meanwhile
                    if time.monotonic() > deadline:
                        log.warning("stopped waiting for the frames in flight after %.0f s: %s", END_WAIT_S, e)
                        break
        self._handle(self.engine.results(0))

    def _frames(self, camera: str | None, source: Source) -> Iterator[Frame]:
        """``source``'s frames for the frame loop: in lockstep read ahead on a thread of their own, so that the
        loop's thread does not decode (Note [Read ahead] in vpengine.io.readahead); as they come otherwise (realtime
        reads each source on a feed thread already, a live source on its own reader)."""
        if self.pace != "lockstep" or source.live:
            return iter(source)
        return ReadAhead(source, READ_AHEAD, self.max_frames, name=f"vpengine-read-{camera or 'camera'}")

    def _end_feeds(self) -> None:
        for f in self.feeds:
            close = getattr(f.frames, "close", None)  # a generator's clean-up (a camera's reader thread)
            if close is not None:
                with contextlib.suppress(ValueError):  # still running in a feed that did not end in time
                    close()
        self._bar.close()
        self.writer.close()  # writes what is queued; raises a sink's error

    # ------------------------------------------------------------------------------------ the loop's steps
    def _submit(self, feed: Feed, frame: Frame, stamp: float | None) -> int:
        fid = next(self._fids)
        self.frames.add(fid, frame.name or f"{fid:06d}", frame.image)
        self.engine.submit(frame.image, frame_id=fid, timestamp=stamp, camera=feed.camera)
        feed.submitted += 1
        feed.last_fid = fid
        return fid

    def _handle(self, results: Iterable[Result]) -> None:
        for r in results:
            key = self.tally.add(r)
            frame, name = self.frames.frame(r.frame_id), self.frames.tag(r.frame_id)
            if self._writes and not self.writer.put(r, frame, name or str(r.frame_id)):
                self.tally.unwritten[key] += 1

    def _progressed(self, done: int) -> None:
        bar = self._bar
        # a disabled bar counts nothing (bar.n stays 0): every frame would read engine.stats() for rates nobody sees
        if not bar.disable and done > bar.n:
            before, after = bar.n // 10, done // 10
            bar.update(done - bar.n)
            if after > before:
                st = self.engine.stats()["models"]
                bar.set_postfix_str(" ".join(f"{n}={m['achieved_hz']:.1f}Hz" for n, m in st.items()), refresh=False)


def run_pipeline(
    config: EngineConfig | str | Path,
    source: Source | Mapping[str | None, Source],
    out_dir: str | Path | None = None,
    **options: Any,
) -> dict[str, Any]:
    """Run ``config`` over ``source`` (:class:`Pipeline`'s arguments); returns the summary."""
    with Pipeline(config, source, out_dir, **options) as pipe:
        return pipe.run()


def video_paths(video: str | Path, cameras: Sequence[str] | None) -> dict[str | None, Path]:
    """Where ``--video PATH`` writes: PATH itself for one camera (key None), ``<stem>_<camera><suffix>`` beside it
    for each of several cameras."""
    p = Path(video)
    if not cameras:
        return {None: p}
    return {c: p.with_name(f"{p.stem}_{c}{p.suffix}") for c in cameras}


@contextlib.contextmanager
def open_sources(
    wanted: Mapping[str | None, tuple[str, str | None]], fps: float | None = None, strict: bool = False
) -> Iterator[dict[str | None, Source]]:
    """Every source wanted (camera name -> (source spec, bag topic)), open for the block (closed after it, also when
    one fails to open)."""
    from vpengine.io.sources import open_source

    with contextlib.ExitStack() as stack:
        yield {
            camera: stack.enter_context(open_source(spec, topic=topic, fps=fps, strict=strict))
            for camera, (spec, topic) in wanted.items()
        }
