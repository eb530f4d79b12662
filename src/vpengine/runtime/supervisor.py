"""Supervision shared by the thread and process runners: READY, death, restart with backoff, stop.

A runner owns one worker per model. When a worker dies (an exception in its model, SIGKILL, a hang that the
runner killed, an exit nobody asked for), the runner releases the pins it held in its input ring, forgets any slot
it left half-written in its output ring, so the models next to it never block, and counts the frames it took but
never finished as dropped; then it restarts the worker after a backoff that doubles with each restart in the last
``RESTART_WINDOW_S`` (a minute). A worker restarted ``runtime.max_restarts`` times within that window is in a crash
loop: it is marked ``failed`` in ``stats()`` and the rest of the engine goes on without it.

Note [Start progress]
~~~~~~~~~~~~~~~~~~~~~
A first start compiles each model (Note [One compile for every batch] in backends/compiled.py) and captures a CUDA
graph for every batch size up to its cameras: with eight cameras, minutes (in thread mode one model after another,
Note [One build at a time] in models/build.py). A fixed deadline either fails a start that is only slow or waits as
long for one that hangs. So a building worker reports each step (the load begun, each batch size run in the
compile's warm-up, each graph captured: ``Executor.progress``) in its
control-block entry, ``build_done`` of ``build_total`` and its heartbeat, and ``start`` (and ``add_head``) give up
after ``runtime.ready_timeout_s`` *without a step* by any worker still loading or by the build they wait behind (in
thread mode the build lock's holder, which may be another engine's; one becoming ready counts too: the next behind
it starts then), and a waiter for the build lock likewise waits while the holder steps. Only the compile backend
counts steps; an eager or ONNX model builds in one. A hang (no step for ``ready_timeout_s``) still ends the start,
with the error naming who was not ready. Meanwhile the logger ``vpengine.start`` says every ``PROGRESS_S`` where
each model is (the CLI shows it).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

from vpengine.config import EngineConfig
from vpengine.runtime.control import FAILED, POLL_S, RESTARTING, STOPPED, ControlBlock
from vpengine.runtime.worker import WorkerSpec
from vpengine.transport.ring import SlotRing

log = logging.getLogger("vpengine.supervisor")

#: The first restart delay; it doubles with each restart in the window, up to RESTART_BACKOFF_MAX_S.
RESTART_BACKOFF_S = 0.5
#: The longest wait before a restart.
RESTART_BACKOFF_MAX_S = 10.0
#: How often a start that waits says where each model is (Note [Start progress]).
PROGRESS_S = 10.0
progress_log = logging.getLogger("vpengine.start")
#: How long a restart counts against ``runtime.max_restarts`` (and doubles the next delay): a worker that fails now
#: and then is restarted every time, one in a crash loop is marked failed.
RESTART_WINDOW_S = 60.0


class EngineStartError(RuntimeError):
    """A worker failed to load or warm up; the message carries the worker's own traceback."""


class EngineDeadError(RuntimeError):
    """The engine was stopped or its foundation model has failed for good; it cannot serve."""


@dataclass
class _Restart:
    due: float


def log_to_file(path: str, level: str, source: str) -> logging.Handler:
    """Send vpengine's log records at ``level`` and above to ``path`` too (appended; every worker process of an
    engine appends to the same file, a line per record). ``source`` names the writer in each line. The vpengine
    logger is lowered to ``level`` if it would drop such records before they reach the file."""
    file = Path(path).expanduser()
    try:
        file.parent.mkdir(parents=True, exist_ok=True)
        handler = logging.FileHandler(file, mode="a", encoding="utf-8")
    except OSError as e:
        raise EngineStartError(f"logging.file {str(file)!r} cannot be written: {e.strerror or e}") from None
    handler.setLevel(level)
    handler.setFormatter(logging.Formatter(f"%(asctime)s %(levelname)s [{source}] %(name)s: %(message)s"))
    logger = logging.getLogger("vpengine")
    handler.level_before = logger.level  # type: ignore[attr-defined]  # restored by close_log_file
    if logger.getEffectiveLevel() > handler.level:
        logger.setLevel(handler.level)
    logger.addHandler(handler)
    return handler


def close_log_file(handler: logging.Handler) -> None:
    """Undo ``log_to_file``: the handler removed and closed, and the vpengine logger's level as it was (a host
    program's logging is its own again once the engine stops)."""
    logger = logging.getLogger("vpengine")
    logger.removeHandler(handler)
    logger.setLevel(getattr(handler, "level_before", logger.level))
    handler.close()


class StartWait:
    """Note [Start progress]: when a wait for models to be ready gives up, and what it says meanwhile. ``what``:
    the wait, in words ("starting", "adding 'det'")."""

    def __init__(
        self,
        control: ControlBlock,
        names: list[str],
        limit: float,
        what: str,
        elsewhere: Callable[[], float] = lambda: 0.0,
    ) -> None:
        """``elsewhere``: when a build they wait behind last made progress (thread mode: the build lock's holder,
        which may be another engine's)."""
        self.control, self.names, self.limit, self.what = control, names, limit, what
        self.elsewhere = elsewhere
        self.t0 = self._said = self._done_at = time.monotonic()
        self._left = len(names)

    def remaining(self, waiting: list[str]) -> float:
        """Seconds left before the wait for ``waiting`` gives up (0: now): ``limit`` after the last step of any of
        them or of a build they wait behind, the last time one of the others became ready (those behind it in the
        build lock's queue start then), or the wait's start. Says where each model is when ``PROGRESS_S`` has
        passed since it last did."""
        now = time.monotonic()
        if len(waiting) < self._left:
            self._left, self._done_at = len(waiting), now
        last = max([self._done_at, self.elsewhere(), *(self.control.get(n, "heartbeat") for n in waiting)])
        if now - self._said >= PROGRESS_S:
            self._said = now
            progress_log.info("%s", self.describe(now))
        return max(0.0, last + self.limit - now)

    def describe(self, now: float) -> str:
        parts, counted = [], False
        for name in self.names:
            state = self.control.state(name)
            done, total = self.control.get(name, "build_done"), self.control.get(name, "build_total")
            counted |= total > 0
            if state in ("ready", "running", "paused"):
                parts.append(f"{name} ready")
            elif state == "loading" and total > 0:
                parts.append(f"{name} {done} of {total} steps")
            else:
                parts.append(f"{name} {state}")
        note = (
            " (a first start compiles each model for its batch sizes; later starts read the compile cache)"
            if counted
            else ""
        )
        return f"{self.what}, {now - self.t0:.0f} s: {', '.join(parts)}{note}"


class Runner(ABC):
    def __init__(
        self, specs: list[WorkerSpec], rings: dict[str, SlotRing], control: ControlBlock, cfg: EngineConfig
    ) -> None:
        self.specs = {s.name: s for s in specs}
        self.rings = rings
        self.control = control
        self.cfg = cfg
        self._lock = threading.RLock()
        self._stopping = False
        self._restarted_at: dict[str, collections.deque[float]] = {s.name: collections.deque() for s in specs}
        self._pending: dict[str, _Restart] = {}
        self._monitor: threading.Thread | None = None  # runs _watch once every worker is ready
        # workers added at run time, until ready or failed: name -> (done, its start-up error or None)
        self._adding: dict[str, tuple[threading.Event, list[str]]] = {}
        self._removing: set[str] = set()  # workers being removed at run time

    # --------------------------------------------------------------------------------------- interface
    @abstractmethod
    def start(self) -> None:
        """Start every worker and wait until all are READY (or raise EngineStartError)."""

    @abstractmethod
    def stop(self) -> list[str]:
        """Stop every worker; always returns. Returns names of workers that had to be killed or abandoned."""

    @abstractmethod
    def _launch(self, name: str) -> None:
        """(Re)start one worker without waiting for READY."""

    @abstractmethod
    def _watch(self) -> None:
        """The monitor's loop, until stop: notice deaths and hangs, run due restarts."""

    @abstractmethod
    def _retire(self, name: str) -> list[threading.Thread]:
        """Stop one worker and forget it (a head removed); returns threads that may still touch the mailboxes.
        Called without the lock held (the process runner waits there for its monitor); the caller takes it for the
        forgetting afterwards."""

    # ------------------------------------------------------------------------------ heads at run time
    def beside_serving(self) -> contextlib.AbstractContextManager[None]:
        """Around Python work of the engine's process while the workers serve (a head added, a worker rebuilt):
        what keeps it from stalling them. Nothing here: workers in processes of their own are not stalled by it."""
        return contextlib.nullcontext()

    def add(self, spec: WorkerSpec, out_ring: SlotRing) -> None:
        """Start the worker of a head added at run time (Note [Heads at run time] in lanes.py) and wait until it is
        ready. EngineStartError with its start-up error if it is not, EngineDeadError if the engine stops meanwhile;
        then the caller takes it away again with ``remove``."""
        name = spec.name
        done: tuple[threading.Event, list[str]] = (threading.Event(), [])
        with self._lock:
            if self._stopping:
                raise EngineDeadError("engine is stopped")
            self.cfg = EngineConfig.model_validate(spec.config)  # the engine's config now: with the head
            self.specs[name] = spec
            self.rings[out_ring.name] = out_ring
            self._restarted_at[name] = collections.deque()
            self._adding[name] = done
            try:
                self._launch(name)
            except BaseException as e:
                done[1].append(f"{name}: {e}")
                done[0].set()
        limit = self.cfg.runtime.ready_timeout_s
        waited = StartWait(self.control, [name], limit, f"adding {name!r}", self.build_progress)
        while not done[0].is_set() and (left := waited.remaining([name])) > 0:
            done[0].wait(min(left, POLL_S))
        ready = done[0].is_set()
        with self._lock:  # the monitor reports under the lock: nothing it heard is lost between here and there
            self._adding.pop(name, None)
            errors = (
                list(done[1])
                if ready
                else [
                    f"{name} was not ready: no progress for {limit} s (runtime.ready_timeout_s){self.build_lock_note()}"
                ]
            )
            stopping = self._stopping
        if stopping:
            raise EngineDeadError(f"engine stopped while {name} was being added")
        if errors:
            raise EngineStartError("\n".join(errors))

    def _abandon_adds(self) -> None:
        """At stop: a head being added will not be ready; its ``add`` returns now (and raises)."""
        with self._lock:
            for done in self._adding.values():
                done[0].set()

    def _added(self, name: str, error: str | None) -> bool:
        """The monitor heard that worker ``name`` is ready (``error`` None) or failed to start; True if it is one
        being added (then it is the caller of ``add``'s to handle, not restarted)."""
        with self._lock:
            done = self._adding.get(name)
            if done is None:
                return False
            if error is not None:
                done[1].append(error)
            done[0].set()
            return True

    def remove(self, name: str) -> list[threading.Thread]:
        """Stop worker ``name`` for good and forget it (a head removed at run time): no restart, its pins released,
        its unanswered frames answered. Returns threads that may still touch the mailboxes (a thread-mode model that
        did not return within runtime.stop_timeout_s)."""
        with self._lock:
            self._pending.pop(name, None)
            self._removing.add(name)  # its exit is no crash: no restart
        left = self._retire(name)
        with self._lock:
            self._removing.discard(name)
            self._cleanup_after(name)
            self.control.set_state(name, STOPPED)
            self.specs.pop(name)  # its output mailbox stays in ``rings``: its owner unmaps it
            self._restarted_at.pop(name, None)
        return left

    def _started(self, errors: list[str]) -> None:
        """The end of ``start``, every worker heard from: ``errors`` (their start-up failures) stop them all and
        raise; else the monitor starts watching them."""
        if errors:
            self.stop()
            raise EngineStartError("worker start-up failed:\n" + "\n".join(errors))
        self._monitor = threading.Thread(target=self._watch, name="vpengine-monitor", daemon=True)
        self._monitor.start()

    def _not_ready(self, waiting: set[str]) -> NoReturn:
        """``start`` waited for ``waiting`` past ``runtime.ready_timeout_s`` without a step of their builds (Note
        [Start progress]): stop every worker and raise."""
        note = self.build_lock_note()
        self.stop()
        raise EngineStartError(
            f"workers {sorted(waiting)} were not ready: no progress for {self.cfg.runtime.ready_timeout_s} s "
            f"(runtime.ready_timeout_s){note}"
        )

    def build_progress(self) -> float:
        """When a build this runner's workers may wait behind last made progress (Note [Start progress]): none by
        default (each worker process builds alone); thread mode: this process's build lock's holder."""
        return 0.0

    def build_lock_note(self) -> str:
        """Why a start may be slow beyond this runner's workers: none by default (each worker process builds
        alone); thread mode names who holds this process's build lock (Note [One build at a time])."""
        return ""

    @property
    def stopping(self) -> bool:
        return self._stopping

    def alive(self, name: str) -> bool:
        return self.control.state(name) not in ("failed", "stopped")

    def threads_alive(self) -> list[threading.Thread]:
        """Threads of this runner that may still touch the mailboxes after ``stop`` returned (Note [Unmapping at
        stop] in runtime/fence.py)."""
        return []

    # ------------------------------------------------------------------------------------- death handling
    def _cleanup_after(self, name: str) -> None:
        """Release what a dead worker held so its neighbours never wait on it, and answer the frame it held (in
        flight, or held for its camera's next batch): it will never run, and ``Engine.wait`` must not wait for it
        (Note [Answered frames] in worker.py)."""
        spec = self.specs[name]
        in_ring = self.rings[spec.in_ring.name]
        out_ring = self.rings[spec.out_ring.name]
        for lane in spec.lanes:
            origin = in_ring.release_reader(lane.reader)
            if origin is not None and origin > self.control.get(lane.entry, "decided"):
                self.control.decide(lane.entry, origin, ran=False)
        out_ring.reset_writer()
        self._count_lost_frames(name)

    def _count_lost_frames(self, name: str) -> None:
        """Count as dropped the frames a dead worker took from its input but never ran, skipped or dropped (the
        one in flight when it died, those it had overtaken on the way): every frame a model saw ends in exactly one
        of ``runs``, ``skipped`` and ``dropped``. Its counters are final (it is gone) and its successor is not
        started yet, so they still have one writer at a time."""
        readers = self.rings[self.specs[name].in_ring.name].stats()["readers"]
        ctl = self.control
        for lane in self.specs[name].lanes:
            reader = readers[lane.reader]  # type: ignore[index]
            seen = reader["reads"] + reader["missed"]
            lost = seen - ctl.get(lane.entry, "runs") - ctl.get(lane.entry, "skipped") - ctl.get(lane.entry, "dropped")
            if lost > 0:
                ctl.add(lane.entry, "dropped", lost)

    def _on_exit(self, name: str, crashed: bool, reason: str) -> None:
        """Called by the runner's monitor when a worker is gone."""
        with self._lock:
            if name in self._removing:
                return  # Runner.remove cleans up after it
            self._cleanup_after(name)
            if self._stopping:
                return
            if crashed:
                self.control.add(name, "crashes")
            now = time.monotonic()
            recent = self._restarted_at[name]
            while recent and recent[0] < now - RESTART_WINDOW_S:  # older restarts no longer count
                recent.popleft()
            n, limit = len(recent), self.cfg.runtime.max_restarts
            if n >= limit:
                self.control.set_state(name, FAILED)
                log.error(
                    "%s failed for good after %d restarts within %.0f s: %s",
                    name,
                    n,
                    RESTART_WINDOW_S,
                    reason,
                )
                return
            delay = min(RESTART_BACKOFF_S * 2 ** min(n, 32), RESTART_BACKOFF_MAX_S)
            self._pending[name] = _Restart(now + delay)
            self.control.set_state(name, RESTARTING)
            log.warning(
                "%s stopped (%s); restart %d/%d within %.0f s, in %.1f s",
                name,
                reason,
                n + 1,
                limit,
                RESTART_WINDOW_S,
                delay,
            )

    def _launch_failed(self, name: str, reason: str) -> None:
        """A restart of ``name`` could not launch it: a crash like any other."""
        self._on_exit(name, True, reason)

    def _run_due_restarts(self) -> float:
        """Launch restarts whose time has come; return seconds until the next one (inf if none)."""
        with self._lock:
            now = time.monotonic()
            nxt = float("inf")
            for name, r in list(self._pending.items()):
                if self._stopping:
                    self._pending.clear()
                    break
                if r.due <= now:
                    del self._pending[name]
                    self._restarted_at[name].append(now)
                    self.control.add(name, "restarts")
                    try:
                        self._launch(name)
                    except Exception as e:  # a failed launch counts as a crash
                        log.error("%s could not be restarted: %s", name, e)
                        self._launch_failed(name, f"restart failed: {e}")
                else:
                    nxt = min(nxt, r.due - now)
            return nxt
