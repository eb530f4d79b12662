"""Thread mode: every model in its own thread (and CUDA stream) of one process, same loop as process mode.

Note [Hung threads]
~~~~~~~~~~~~~~~~~~~
A Python thread cannot be killed, so a model hung in its forward (a deadlock, a C call that never returns) cannot be
taken back as in process mode. What can be done is done: once its heartbeat is older than
``runtime.hang_timeout_s`` the model is marked ``hung`` (``stats()``: state, a crash counted, the reason in
``last_error``), ``Engine.wait`` no longer waits for it, and the rest of the engine goes on (the frame it holds
is one of the slots its mailbox keeps for each reader, so nobody waits for it). Its thread is told to leave: if it
ever returns, it finishes that frame and exits, and the model is restarted on a fresh thread and stream under the
restart rules. Until then the thread keeps its frame, its output slot and its memory, and a thread hung while holding
the GIL stops the whole process (process mode isolates that). At ``stop()`` a hung thread is abandoned (a daemon
thread); the mailboxes stay mapped until it ends (Note [Unmapping at stop] in fence.py).

Note [Building beside serving threads]
~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~
A model built while others serve (a head added at run time, a restart) runs seconds of Python in its thread:
dynamo's tracing, inductor's lowering and code generation (sympy), cache and kernel loads. It stalls the serving
threads in three ways, all seen on an H200 in thread mode while the first compiled detection head was added to the
shipped bench config (process mode: no stall):

* The switch interval. A serving worker gives up Python's interpreter lock many times a frame (every wait on its
  mailbox, an event, the device), and each time it wants it back it waits until the builder is made to drop it,
  once per switch interval (5 ms by default): a frame of a few dozen waits then takes hundreds of milliseconds.
  While a thread builds beside serving ones the interval is ``BUILD_SWITCH_INTERVAL_S`` (a tenth of the default),
  which costs the builder only the switches that a serving thread asks for.
* The garbage collector. A build makes many objects that live on, so the collector runs full collections, and a
  full collection walks every object of the process (hundreds of thousands once torch is loaded) with the lock
  held: no thread runs meanwhile. With the switch interval short, the serving threads still stopped for many frame
  periods a few times per (cold) build, and so did a thread that only woke every 10 ms: the whole interpreter
  stopped. Freezing the heap for the build (``gc.freeze``) was not enough: a first compiled add makes enough
  lasting objects (dynamo's graphs and guards, inductor's kernels) that one full collection of those alone stopped
  every serving thread for many frame periods. So while a thread builds beside serving ones no full collection runs
  (young collections do: they walk only young objects), and when the last build ends its young garbage is collected
  and what it made is frozen with the rest, so no later full collection walks it either. The heap stays frozen
  while the engines that built beside serving threads run, and is unfrozen when the last of them stops (nothing of
  theirs serves then), unless the program had frozen it itself: that heap stays frozen. The cost is the cyclic
  garbage in the old generation when a build ends, kept until that stop; a removed head's model is freed by
  reference counting, not by the collector (tested with the collector off). A Python whose collector is incremental
  (3.14.0 to 3.14.4) ignores the threshold that holds full collections off; its collections walk a part of the old
  generation at a time instead. A free-threaded Python walks the whole heap in every collection.

* Compiles in this thread. Inductor compiles Triton kernels in its worker processes only once their pool is up;
  before that, Triton's LLVM passes ran in the builder and held the lock 56-73 ms a kernel, even with a warm compile
  cache. A compiled model built beside serving threads waits for the pool first (Note [Compile workers] in
  backends/compiled.py). What still holds the lock for tens of milliseconds at once (dynamo building a model's
  guards, a generated module's byte-compile) is torch's and stays.

The first two are process-wide, so they are set by the first of the threads that build at once and undone after the last
(a build that never returns, Note [Hung threads], leaves them set: no full collection runs until it returns).
They cover the whole of ``Engine.add_head`` (``Runner.beside_serving``): its planning builds the head on the meta
device in the caller's thread, which on a first add imports much of torch's compiler stack. Building at start needs
neither: nothing serves yet.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator

from vpengine.models.build import build_lock
from vpengine.runtime.control import HUNG, POLL_S, STOPPED
from vpengine.runtime.handoff import Handoffs
from vpengine.runtime.prepare import prepare_worker
from vpengine.runtime.supervisor import Runner, StartWait
from vpengine.runtime.worker import describe_exception

log = logging.getLogger("vpengine.threads")

#: The switch interval while a model is built beside serving threads (Note [Building beside serving threads]).
BUILD_SWITCH_INTERVAL_S = 0.0005


#: Gen-2 threshold while a build runs beside serving threads: no full collection (Note [Building beside serving
#: threads]); the young generations keep theirs.
_NO_FULL_COLLECTION = 2**31 - 1


class _Builders:
    """How many threads build beside serving ones and what the first of them changed, to undo after the last; which
    engines keep the heap frozen (Note [Building beside serving threads])."""

    def __init__(self) -> None:
        # re-entrant: a collection run inside (ours, or one an allocation starts) may finalise an abandoned engine,
        # whose stop releases its holder from this thread
        self.lock = threading.RLock()
        self.busy = False  # changing the collector's state: a release from inside only drops its holder
        self.count = 0
        self.interval = sys.getswitchinterval()
        self.thresholds = gc.get_threshold()
        self.holders: set[int] = set()  # id() of the runners whose builds' objects are frozen
        self.ours = False  # the frozen heap is ours to unfreeze: nobody had frozen it before the first holder

    def release(self, holder: int) -> None:
        """``holder`` stopped: unfreeze the heap if it was the last holder, no build runs and the heap is ours."""
        with self.lock:
            self.holders.discard(holder)
            if not self.busy:  # else the change under way ends with this check
                self._unfreeze_if_unheld()

    def enter(self, holder: int, stopping: Callable[[], bool]) -> None:
        with self.lock:
            self.busy = True
            try:
                self.count += 1
                if self.count == 1:
                    self.interval = sys.getswitchinterval()
                    sys.setswitchinterval(min(BUILD_SWITCH_INTERVAL_S, self.interval))
                    self.thresholds = gc.get_threshold()
                    gc.set_threshold(self.thresholds[0], self.thresholds[1], _NO_FULL_COLLECTION)
                    if not self.holders:
                        self.ours = gc.get_freeze_count() == 0  # a heap the program froze itself stays frozen
                    gc.freeze()
                if not stopping():  # checked under the lock that release takes: no holder added after its release
                    self.holders.add(holder)
            except BaseException:  # a Ctrl-C halfway: undo what was done
                self._leave()
                raise
            finally:
                self.busy = False

    def leave(self) -> None:
        with self.lock:
            self._leave()

    def _leave(self) -> None:
        self.busy = True
        try:
            self.count -= 1
            if self.count == 0:
                try:
                    sys.setswitchinterval(self.interval)
                    gc.collect(1)  # the builds' young garbage: walks only the young generations
                    gc.freeze()
                finally:
                    gc.set_threshold(*self.thresholds)
        finally:
            self.busy = False
        self._unfreeze_if_unheld()  # every holder stopped while it built

    def _unfreeze_if_unheld(self) -> None:
        if not self.holders and self.count == 0 and self.ours:
            gc.unfreeze()
            self.ours = False


_builders = _Builders()


@contextlib.contextmanager
def _beside_serving(holder: int, stopping: Callable[[], bool] = lambda: False) -> Iterator[None]:
    """Note [Building beside serving threads]: a short switch interval and no full collection until the last builder
    is done; then what the builds made is frozen until ``holder`` (and every other holder) stops. A holder that is
    ``stopping()`` already has made its release: it holds nothing."""
    _builders.enter(holder, stopping)
    try:
        yield
    finally:
        _builders.leave()


class ThreadRunner(Runner):
    def __init__(  # type: ignore[no-untyped-def]
        self, *args, handoffs: Handoffs | None = None, **kw
    ) -> None:
        super().__init__(*args, **kw)
        # what the workers hand each other on the device and the submitting thread (handoff.py)
        self.handoffs = handoffs or Handoffs()
        self._threads: dict[str, threading.Thread] = {}
        # (name, "ready"|"error"|"exit", text, the thread's generation)
        self._events: queue.Queue[tuple[str, str, str, int]] = queue.Queue()
        self._retired_gen: dict[str, int] = {}  # a removed head's last generation: its threads' events are stale
        self._generation: dict[str, int] = dict.fromkeys(self.specs, 0)
        self._hung: set[str] = set()  # Note [Hung threads]: told to leave, not gone yet

    def beside_serving(self) -> contextlib.AbstractContextManager[None]:
        return _beside_serving(id(self), lambda: self._stopping)

    def build_progress(self) -> float:
        return build_lock.stepped if build_lock.holder() else 0.0

    def build_lock_note(self) -> str:
        holder = build_lock.holder()
        return f"; {holder} holds this process's build lock (Note [One build at a time])" if holder else ""

    def _should_stop(self, name: str, gen: int) -> bool:
        return self._stopping or self.control.stopping or self._generation[name] != gen

    def _main(self, name: str, gen: int) -> None:
        spec = self.specs[name]
        # others serve once the monitor watches: a head added, a restart (Note [Building beside serving threads])
        serving = self._monitor is not None
        try:
            with self.beside_serving() if serving else contextlib.nullcontext():
                core = prepare_worker(
                    spec,
                    self.rings[spec.in_ring.name],
                    self.rings[spec.out_ring.name],
                    self.control,
                    own_process=False,
                    handoff=self.handoffs.for_worker(name),
                    cancelled=lambda: self._should_stop(name, gen),
                    beside_serving=serving,
                )
        except BaseException as e:
            self._events.put((name, "error", describe_exception(name, e), gen))
            return
        self._events.put((name, "ready", "", gen))
        try:
            core.run(lambda: self._should_stop(name, gen))
        except BaseException as e:
            if gen <= self._retired_gen.get(name, 0):
                return  # its head was removed, and its names may be another's now: it leaves without a word
            text = describe_exception(name, e)
            self.control.add(name, "errors")
            self.control.set_error(name, text)
            self._events.put((name, "exit", text, gen))
            return
        self._events.put((name, "exit", "", gen))

    def _launch(self, name: str) -> None:
        self._generation[name] = self._generation.get(name, 0) + 1
        t = threading.Thread(
            target=self._main, args=(name, self._generation[name]), name=f"vpengine-{name}", daemon=True
        )
        self._threads[name] = t
        t.start()

    def start(self) -> None:
        import torch

        if self.cfg.device == "cpu":
            # Intra-op threads are per process: in thread mode all models share one pool, sized like a worker's.
            torch.set_num_threads(self.cfg.foundation_model.cpu_threads)
        for name in self.specs:
            self._launch(name)
        waiting = set(self.specs)
        waited = StartWait(
            self.control, list(self.specs), self.cfg.runtime.ready_timeout_s, "starting", self.build_progress
        )
        errors = []
        while waiting:
            left = waited.remaining(list(waiting))  # Note [Start progress]
            if left <= 0:
                self._not_ready(waiting)
            try:
                name, kind, text, _ = self._events.get(timeout=min(left, POLL_S))
            except queue.Empty:
                continue
            waiting.discard(name)
            if kind != "ready":
                errors.append(text or f"{name} exited during start-up")
        self._started(errors)

    def _watch(self) -> None:
        while not self._stopping:
            timeout = min(self._run_due_restarts(), POLL_S)
            try:
                name, kind, text, gen = self._events.get(timeout=max(0.01, timeout))
            except queue.Empty:
                self._check_hangs()
                continue
            if name not in self.specs or name in self._removing or gen <= self._retired_gen.get(name, 0):
                continue  # stop's wake-up, or a removed head's (its exit is expected)
            if kind == "ready":
                self._added(name, None)
            elif self._added(name, text or f"{name} exited during start-up"):
                pass  # a head being added failed to start: add() takes it away again
            elif kind == "exit" and not self._stopping:
                first_line = text.splitlines()[0] if text else "exited"
                with self._lock:
                    was_hung = name in self._hung  # its crash was counted when it was found hung
                    self._hung.discard(name)
                self._on_exit(name, crashed=bool(text) and not was_hung, reason=first_line)
            elif kind == "error" and not self._stopping:
                self._on_exit(name, crashed=True, reason=text.splitlines()[0])
            self._check_hangs()

    def _check_hangs(self) -> None:
        """Note [Hung threads]: mark a model whose heartbeat is older than ``runtime.hang_timeout_s`` hung."""
        limit = self.cfg.runtime.hang_timeout_s
        if limit is None:
            return
        now = time.monotonic()
        with self._lock:
            for name, t in self._threads.items():
                if self._stopping or name in self._pending or name in self._hung or not t.is_alive():
                    continue
                if self.control.state(name) not in ("running", "paused"):
                    continue  # loading (a build can take long) or already handled
                hb = self.control.get(name, "heartbeat")
                if hb <= 0 or now - hb <= limit:
                    continue
                self._hung.add(name)
                self._generation[name] += 1  # its thread leaves if it ever returns
                text = (
                    f"{name}: hung for {now - hb:.0f} s (runtime.hang_timeout_s = {limit:g} s); a thread cannot be "
                    "killed: restarted if it returns"
                )
                self.control.set_state(name, HUNG)
                self.control.add(name, "crashes")
                self.control.set_error(name, text)
                log.error("%s", text)

    def _retire(self, name: str) -> list[threading.Thread]:
        with self._lock:
            self._retired_gen[name] = self._generation[name]
            self._generation[name] += 1  # its loop ends at its next look
            self._hung.discard(name)
            thread = self._threads.pop(name, None)
        for ring in list(self.rings.values()):  # a head added or removed meanwhile changes the dict
            ring.wake_all()  # a worker asleep on its mailbox looks now
        if thread is None:
            return []
        thread.join(self.cfg.runtime.stop_timeout_s)
        if thread.is_alive():
            log.error("%s did not stop within %.1f s; abandoned (daemon thread)", name, self.cfg.runtime.stop_timeout_s)
            return [thread]
        return []

    def threads_alive(self) -> list[threading.Thread]:
        threads = [t for t in self._threads.values() if t.is_alive()]
        if self._monitor is not None and self._monitor.is_alive():
            threads.append(self._monitor)
        return threads

    def stop(self) -> list[str]:
        with self._lock:
            self._stopping = True
            threads = list(self._threads.items())  # add() may launch one meanwhile
        self._abandon_adds()
        self.control.request_stop()
        for ring in list(self.rings.values()):  # a head added or removed meanwhile changes the dict
            ring.wake_all()
        if self.handoffs.inline is not None:
            self.handoffs.inline.wake()  # an armed foundation worker disarms and sees the stop
        self._events.put(("", "stop", "", 0))  # the monitor leaves now, not at its next poll
        deadline = time.monotonic() + self.cfg.runtime.stop_timeout_s
        abandoned = []
        for name, t in threads:
            t.join(max(0.0, deadline - time.monotonic()))
            if t.is_alive():
                abandoned.append(name)
            else:
                self.control.set_state(name, STOPPED)
        if self._monitor is not None:
            self._monitor.join(2.0)
        if abandoned:
            log.error(
                "threads %s did not stop within %.1f s; abandoned (daemon threads)",
                abandoned,
                self.cfg.runtime.stop_timeout_s,
            )
        _builders.release(id(self))  # Note [Building beside serving threads]: nothing of ours serves now
        return abandoned
