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
    last_fid: int | None = None  # the frame id of its last frame submitted


@dataclass
class FrameLoop:
    """What both pacings take: the feeds, when to stop, and the pipeline's three steps (``submit`` a feed's frame
    and return its frame id, ``handle`` results, report ``progressed`` frames). Lockstep calls ``handle`` and
    ``progressed`` on its answering thread (Note [Answering thread]), realtime on the loop's."""

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
    answers = Answers(loop)
    try:
        try:
            while active and answers.room() and not loop.stop.is_set():
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
                    answers.put(fids)
        except Exception:
            answers.finish()  # a source that failed (--strict): the frames before it are answered and written first
            raise
        answers.finish()  # the frames in hand are answered, after the last frame or a Ctrl-C alike
    except BaseException as e:
        if not isinstance(e, Exception):  # a second Ctrl-C, also while finishing: at once, as a head that never
            answers.abandon()  # answers must not hold it up
        raise


class Answers:
    """Note [Answering thread]: a lockstep loop's thread used to submit a round, wait for the oldest round's outputs
    (which maps them back to each frame's grid, Note [Frame grid]) and hand them on, one after the other, so a run
    went at the sum of those host steps even when the models were faster. Here a thread of its own answers the
    rounds (``engine.wait`` and ``handle`` of each frame, then the progress count) in the order they were submitted,
    while the loop reads and submits the next ones; a run goes at the slower of the two. Nothing of Note [Frames in
    flight] changes: ``room`` lets the loop submit a round only while fewer than ``in_flight`` rounds have outputs
    still in the mailboxes (a round counts until its frames' outputs are taken out, before they are handled), so no
    frame nobody has taken is overwritten; results are handled in frame order, on one thread, as before. An error
    on the answering side (a dead engine, a sink that failed) ends the answering there and is raised in the loop at
    its next ``room`` or at ``finish``; a wait that times out is logged and the run goes on, as before."""

    def __init__(self, loop: FrameLoop) -> None:
        self._loop = loop
        self._cond = threading.Condition()
        self._rounds: collections.deque[list[int]] = collections.deque()  # submitted, not yet taken, oldest first
        self._ending = False  # no more rounds come
        self._abandoned = False
        self._error: BaseException | None = None
        self._raised = False  # raised in the loop once already (finish does not raise it again)
        self._thread = threading.Thread(target=self._answer, name="vpengine-answers", daemon=True)
        self._thread.start()

    def room(self) -> bool:
        """Wait until the loop may submit another round (Note [Frames in flight]); raises the answering side's
        error. False once the loop should stop (Ctrl-C)."""
        with self._cond:
            # in slices: a Ctrl-C sets stop without a notify
            while len(self._rounds) >= self._loop.in_flight and self._error is None and not self._loop.stop.is_set():
                self._cond.wait(0.1)
            self._raise()
        return not self._loop.stop.is_set()

    def put(self, fids: list[int]) -> None:
        with self._cond:
            self._rounds.append(fids)
            self._cond.notify_all()

    def finish(self) -> None:
        """Answer every round submitted, then raise the answering side's error if it had one."""
        with self._cond:
            self._ending = True
            self._cond.notify_all()
        while self._thread.is_alive():
            self._thread.join(0.1)  # in slices, as in room
        self._raise()

    def abandon(self) -> None:
        """Answer and handle nothing more; the thread ends once a wait in progress returns (the engine stops)."""
        with self._cond:
            self._abandoned = True
            self._cond.notify_all()

    def _raise(self) -> None:
        if self._error is not None and not self._raised:
            self._raised = True
            raise self._error

    def _answer(self) -> None:
        loop, done = self._loop, 0
        try:
            while True:
                with self._cond:
                    while not self._rounds and not self._ending and not self._abandoned:
                        self._cond.wait()
                    if self._abandoned or not self._rounds:
                        return
                    fids = self._rounds[0]  # counted in flight until its outputs are taken
                answered = []
                for fid in fids:
                    try:
                        answered.append(loop.engine.wait(fid, timeout=60.0))
                    except TimeoutError as e:
                        log.warning("%s", e)
                with self._cond:
                    self._rounds.popleft()
                    self._cond.notify_all()
                    if self._abandoned:
                        return
                for results in answered:
                    loop.handle(results.values())
                done += len(fids)
                loop.progressed(done)
        except BaseException as e:
            with self._cond:
                self._error = e
                self._cond.notify_all()


# Note [Frames in flight]: lockstep promises every frame through every head, in order, each output paired with its
# frame. One frame at a time keeps that promise, but a run then goes at the sum of the models' latencies rather than
# the pace of the slowest. With several frames in flight a model that reads only the newest frame (input_mode: latest)
# would skip those that queued behind it, so a lockstep run has every model take every frame in order (input_mode:
# fifo) whatever the config says: in lockstep the pipeline, not a camera, decides what queues, so a model sees the
# same frames either way. How many rounds (a frame of each camera): what the mailboxes hold without overwriting a
# frame nobody has taken (a fifo reader's margin, FIFO_MARGIN, and each head's kept results, output.slots), less one
# for the round being submitted. The rounds are answered on a thread of their own (Note [Answering thread]). More
# rounds, with mailboxes to match, were tried with four cameras on a GPU (five and seven a camera): frames per second
# fell in thread and process mode alike, and each frame's results came later.
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
