"""How a pipeline feeds its sources to the engine: lockstep or realtime pacing, one feed per camera, and what
Ctrl-C does to a run (Notes [Several sources] and [Ctrl-C]).
"""

from __future__ import annotations

import collections
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from vpengine.config import EngineConfig, load_config
from vpengine.io.base import Frame, Source
from vpengine.runtime.plan import FIFO_MARGIN

if TYPE_CHECKING:
    from vpengine.engine import Engine
    from vpengine.engine.results import Result

log = logging.getLogger("vpengine.run")


@dataclass
class Feed:
    """One camera's source in the frame loop (Note [Several sources])."""

    camera: str | None  # None: the engine's one camera, unnamed
    source: Source
    period: float  # its pace and the spacing of its stamps when its frames have none
    self_paced: bool  # a live camera without --fps: it delivers at its own rate (Note [Live capture])
    frames: Iterator[Frame]
    submitted: int = 0


@dataclass
class FrameLoop:
    """What both pacings take: the feeds, when to stop, and the pipeline's three steps (``submit`` a feed's frame
    and return its frame id, ``handle`` results, report ``progressed`` frames)."""

    feeds: list[Feed]
    max_frames: int | None
    stop: threading.Event
    submit: Callable[[Feed, Frame, float | None], int]
    engine: Engine
    handle: Callable[[Iterable[Result]], None]
    progressed: Callable[[int], None]
    in_flight: int = 1  # lockstep: rounds submitted and not yet answered, at most (Note [Frames in flight])


# Note [Several sources]: with several cameras (``--source NAME=SPEC`` repeated) each source feeds its own camera,
# on its own timeline: a file's frames are stamped by their position at its own rate, so each camera's rate limits
# hold on its own clock. Lockstep takes the next frame of every source that still has frames, submits them all and
# waits until every head has answered each, then takes the next round: nothing is skipped, and a source that ends
# drops out while the others go on. Realtime feeds each source from a thread of its own at its own rate (a live
# camera at its own pace, Note [Live capture]), as separate cameras would deliver; the loop collects the results.
# One source is the same loop with one feed.
def lockstep(loop: FrameLoop) -> None:
    active = list(loop.feeds)
    rounds: collections.deque[list[int]] = collections.deque()  # submitted, not yet answered, oldest first
    done = 0

    def settle(fids: list[int]) -> None:
        nonlocal done
        for fid in fids:
            try:
                loop.handle(loop.engine.wait(fid, timeout=60.0).values())
            except TimeoutError as e:
                log.warning("%s", e)
        done += len(fids)
        loop.progressed(done)

    try:
        while active and not loop.stop.is_set():
            fids = []
            for feed in list(active):
                frame = None
                if loop.max_frames is None or feed.submitted < loop.max_frames:
                    frame = next(feed.frames, None)
                if frame is None:
                    active.remove(feed)
                    continue
                stamp = frame.timestamp
                if stamp is None:  # a file without stamps: its own timeline at its pace
                    stamp = feed.submitted * feed.period
                fids.append(loop.submit(feed, frame, stamp))
            if fids:
                rounds.append(fids)
            while len(rounds) >= loop.in_flight:
                settle(rounds.popleft())
    except Exception:
        while rounds:  # a source that failed (--strict): the frames before it are answered and written first
            settle(rounds.popleft())
        raise
    while rounds:  # the frames in hand are answered, after the last frame or a Ctrl-C alike
        settle(rounds.popleft())


# Note [Frames in flight]: lockstep promises every frame through every head, in order, each output paired with its
# frame. One frame at a time keeps that promise, but a run then goes at the sum of the models' latencies rather than
# the pace of the slowest. With several frames in flight a model that reads only the newest frame (input_mode: latest)
# would skip those that queued behind it, so a lockstep run has every model take every frame in order (input_mode:
# fifo) whatever the config says: in lockstep the pipeline, not a camera, decides what queues, so a model sees the
# same frames either way. How many rounds (a frame of each camera): what the mailboxes hold without overwriting a
# frame nobody has taken (a fifo reader's margin, FIFO_MARGIN, and each head's kept results, output.slots), less one
# for the round being submitted.
def pipelined(cfg: EngineConfig) -> tuple[EngineConfig, int]:
    """The config a lockstep run uses and how many rounds of frames it keeps in flight (Note [Frames in flight])."""
    overrides = ["foundation_model.input_mode=fifo"] + [f"heads.{h.name}.input_mode=fifo" for h in cfg.heads]
    room = min([FIFO_MARGIN, *(h.output.slots for h in cfg.heads)]) - 1
    return load_config(cfg.model_dump(mode="json"), overrides), max(1, room)


def realtime(loop: FrameLoop) -> None:
    errors: list[BaseException] = []
    stop, max_frames = loop.stop, loop.max_frames

    def feed_loop(feed: Feed) -> None:
        next_t = time.monotonic()
        try:
            for frame in feed.frames:
                if stop.is_set() or (max_frames is not None and feed.submitted >= max_frames):
                    return
                if not feed.self_paced:
                    wait = next_t - time.monotonic()
                    if wait > 0 and stop.wait(wait):
                        return
                    next_t = max(next_t + feed.period, time.monotonic() - feed.period)
                loop.submit(feed, frame, frame.timestamp)
        except BaseException as e:
            errors.append(e)
            stop.set()  # one failed source ends the run, as it did alone

    threads = [
        threading.Thread(target=feed_loop, args=(f,), name=f"vpengine-feed-{f.camera or 'camera'}", daemon=True)
        for f in loop.feeds
    ]
    for t in threads:
        t.start()
    try:
        while any(t.is_alive() for t in threads):
            loop.handle(loop.engine.results(timeout=0.05))
            loop.progressed(sum(f.submitted for f in loop.feeds))
    except BaseException:
        stop.set()  # a second Ctrl-C, a failed writer: the feeds end at their next frame
        raise
    finally:
        for t in threads:
            t.join(timeout=2.0)
    loop.handle(loop.engine.results(0))
    loop.progressed(sum(f.submitted for f in loop.feeds))
    if errors:
        raise errors[0]


@contextmanager
def ctrl_c() -> Iterator[threading.Event]:
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
