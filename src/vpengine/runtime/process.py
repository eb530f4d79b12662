"""Process mode: every model in its own child process.

Note [Child lifecycle]
~~~~~~~~~~~~~~~~~~~~~~
* Workers are forked from a zygote (runtime/zygote.py), never from the engine: the engine may have initialised CUDA,
  and a forked CUDA context is unusable. The zygote is a fresh interpreter, started once per runner, that imports what
  every worker needs (torch, the worker loop, the rings) and then only forks: it never initialises CUDA (it checks
  torch's flag before each fork; a CUDA build of torch maps libcuda at import, which creates no context), runs no
  model and has one Python thread. It is not single-threaded natively: OpenBLAS (numpy's import) keeps a thread per
  extra core, and its pthread_atfork handler quiesces them around each fork, which is what makes the fork safe. A fork
  of it is as clean as a fresh interpreter that has done those imports, so a worker starts, and restarts, without
  paying the import of torch again (seconds of CPU each, more on a Jetson). Unlike multiprocessing's spawn or
  forkserver, the user's ``__main__`` script is never re-imported, so scripts need no ``if __name__ == "__main__"``
  guard and a ROS node's top-level code never runs twice. The zygote and every worker get their own session, so a
  Ctrl-C in the terminal reaches only the engine, which then stops them in order.
* Nothing comes from the working directory: the zygote runs isolated (``python -I``: no current directory or script
  directory on ``sys.path``, no PYTHON* variables, no user site) with an explicit ``sys.path``: the folder of this
  vpengine package, then the engine's ``sys.path`` as absolute paths, so a user head the engine can import
  (``package.module:Class``) a worker imports from the same place. Before, ``python -m`` put the current directory
  first, and a ``yaml.py`` planted in a shared directory ran in every worker. Each start request carries the
  engine's import path, working directory and environment (its own and ``env_for``'s, e.g. the MPS variables) as
  they are at that (re)start; the fork takes them over before it imports anything of the worker's own. The working
  directory stays the engine's (relative checkpoint and log paths mean what they mean to the engine); only imports
  ignore it. An engine whose own ``sys.path`` holds its current directory ('' in a REPL or ``python -c``) passes it
  on: the worker then imports from where the engine already does, nowhere else. The fork invalidates the import
  system's directory caches (they are the zygote's, maybe old) and takes over the engine's CPU affinity as it is at
  that (re)start. What a library read as it loaded stays what the zygote read: ``LOAD_TIME_ENV`` in zygote.py
  (LD_PRELOAD, LD_LIBRARY_PATH, the OpenMP/OpenBLAS/MKL thread counts, TORCH_LOGS); when a start request sets one
  otherwise, a new zygote is started and forks the workers from then on (the old one stays while workers it forked
  live). The rest a worker inherits from the zygote, i.e. from the engine as it was when the zygote started, not as
  it is now: rlimits, umask, nice value, scheduling class, the real and effective ids.
* Each worker holds exactly one file descriptor of ours: its end of a UNIX socketpair, which the engine hands the
  zygote with SCM_RIGHTS in the start request (the zygote closes its copy and its own socket in the fork). Over it
  the engine sends the worker's spec and then the file descriptors of every region it maps (memfds, CUDA VMM
  handles) with SCM_RIGHTS -- no socket file, no /dev/shm name, so no other process can attach -- and both ends
  check the peer's uid with SO_PEERCRED. The worker answers READY (or its traceback) once its model is loaded and
  warmed up; the engine waits while its build makes progress (Note [Start progress] in supervisor.py).
* The same socket is the death pipe: a watcher thread in the worker blocks on it, and when the engine dies (even by
  SIGKILL) the kernel closes the engine's end, the read returns EOF, and the worker exits at once. That needs the
  worker's interpreter to run (not SIGSTOPped, not hung in C code holding the GIL) and no other process to hold the
  engine's end (a helper the user's program forked inherits it). So the kernel kills them too, in a chain: the
  zygote asks for SIGKILL when its parent dies (``PR_SET_PDEATHSIG``) first thing, then checks that the parent is
  still the one that started it (had it died before, nobody would send the signal); each worker does the same
  towards the zygote. The kernel sends the signal when the *thread* that started the process ends, so the zygote
  is started by one spawner thread that lives as long as the runner (the zygote forks from its only thread). Killing
  the engine kills the zygote, which kills the workers; a zygote that dies (a crash, the OOM killer) takes its
  workers with it, and the runner restarts them, from a new zygote. A process forked from the engine gets /dev/null
  in place of the engine's socket ends (``os.register_at_fork``), and its copies of the runner and the zygote
  handle, which record the pid that made them, send no signal and no message: the engine's finalizer runs at the
  exit of a plain ``os.fork()`` child too, and its ``stop()`` only drops references there.
* Only a parent can reap, so the zygote reaps its workers and reports each ``(pid, returncode)`` (``Popen``'s
  convention) to the engine, where a ``WorkerProc`` (zygote_handle.py) stands in for a ``Popen``. The zygote opens
  each worker's pidfd right after the fork, before it can reap it, and sends it with ``Forked`` (SCM_RIGHTS): it
  names that process, never a later one with the same pid. Signals go through it; without pidfds (kernel < 5.3) they
  go as a message to the zygote, which signals only children it has not reaped. The engine never signals a bare pid
  it did not reap. The monitor thread wakes on the reports, the workers' sockets and their pidfds: a worker gone
  (pidfd readable) with no report for ``REPORT_GRACE_S`` (1 s) means the zygote is stopped or stuck; it is killed
  and its workers, dead with an unknown exit code or killed with it, are restarted from a new one. A death is
  handled by ``Runner._on_exit``.
* ``start`` waits for the zygote at most ``runtime.ready_timeout_s``, for each fork's answer at most 30 s
  (milliseconds in practice; a zygote that does not answer is killed), then for READY while the workers' builds
  make progress, at most ``runtime.ready_timeout_s`` after the last step (Note [Start progress] in supervisor.py): a
  build that hangs ends the start ``ready_timeout_s`` after its last step, plus ``stop``'s bound.
* ``stop`` asks politely (stop flag + message) and waits ``runtime.stop_timeout_s``, then SIGTERM and 2 s, then
  SIGKILL and 2 s, all workers together; then the monitor thread gets 2 s; then each zygote gets EOF and 1 s, SIGTERM
  and 0.5 s, SIGKILL and 2 s, and its reader thread 4 s; then the spawner thread 1 s: at most ``stop_timeout_s`` +
  14.5 s (7.5 s more for each older zygote still kept for its workers). It always returns, in practice within
  ``stop_timeout_s``. ``remove_head`` stops one worker the same way, then waits for the monitor to close its socket
  (at most ``stop_timeout_s`` again).

Note [Process groups]
~~~~~~~~~~~~~~~~~~~~~
A CUDA context costs each process several hundred MB of device memory whatever it runs (Note [Thread stack] trims
only a part), so ten workers pay for ten. Models whose configs name the same ``process`` share one worker: it gets
one ``Init`` with all of their specs, maps each mailbox once (the features between a backbone and a head of one
process too), builds them one after another, answers READY when all are, and runs each model's loop on its own
thread and CUDA stream, as thread mode does in the engine's process. The process is the unit of fault isolation: a
model whose loop ends with an error (a CUDA error, Note [Frame errors]), crashes or hangs ends the process, and
every model in it is counted a crash and restarted with it, once: the first model of the process alone has a restart
pending and decides for all (they fail for good together, a launch that fails fails them all); MPS gives the process
the client priority of its most important model. A head added at run time gets a process of its own, and a head that
shares one is not removed while the engine runs (its process would go with it): both are refused with the reason.
Thread mode has one process already and ignores ``process``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import subprocess
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import replace
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

from vpengine.config import EngineConfig
from vpengine.runtime.control import POLL_S, STOPPED
from vpengine.runtime.sockets import (
    Failed,
    Init,
    Ready,
    Stop,
    peer_uid,
    release_parent_end,
    send_fds,
    start_with_socket,
)
from vpengine.runtime.sockets import recv_fds as recv_fds  # where tools and tests have always found it
from vpengine.runtime.supervisor import Runner, StartWait
from vpengine.runtime.zygote import worker_path
from vpengine.runtime.zygote_handle import WorkerProc, Zygote, describe_exit
from vpengine.transport.ring import RingDesc

log = logging.getLogger("vpengine.process")


def package_env() -> dict[str, str]:
    """The environment of a helper process (a tool's, a test's) that imports this package from wherever this one is:
    this environment with the folder holding ``vpengine`` first on PYTHONPATH. Workers do not use it: they start
    isolated, with an explicit path (Note [Child lifecycle])."""
    env = dict(os.environ)
    src = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join([src, *([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])])
    return env


class _Spawner:
    """Starts processes from one thread that lives as long as it is open: a child's parent-death signal comes when
    the thread that started it ends (Note [Child lifecycle]), and restarts and ``start()`` run in threads that may
    end sooner (a user's thread, say)."""

    def __init__(self) -> None:
        self._calls: queue.SimpleQueue[tuple[Callable[[], Any], Future[Any]] | None] = queue.SimpleQueue()
        self._closed = False
        self._thread = threading.Thread(target=self._serve, name="vpengine-spawner", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while (call := self._calls.get()) is not None:
            fn, fut = call
            try:
                fut.set_result(fn())
            except BaseException as e:
                fut.set_exception(e)

    def call(self, fn: Callable[[], Any]) -> Any:
        if self._closed:
            raise RuntimeError("the engine is stopping: no worker is started any more")
        fut: Future[Any] = Future()
        self._calls.put((fn, fut))
        return fut.result()

    def close(self, timeout: float) -> None:
        """End the thread (waiting at most ``timeout``); call once every process it started is gone."""
        self._closed = True
        self._calls.put(None)
        if self._thread is not threading.current_thread():
            self._thread.join(timeout)


class _Child:
    def __init__(self, proc: WorkerProc, conn: Connection, names: tuple[str, ...]) -> None:
        self.proc = proc
        self.conn = conn
        self.names = names  # the models it runs (Note [Process groups])
        self.ready = False
        self.error: str | None = None
        self.eof = False  # its socket reached EOF (it is exiting)
        self.handled = False  # its death was handled (cleanup, restart scheduled)
        self.killed = False  # killed for a hang: once

    def alive(self) -> bool:
        """Not reported gone by the zygote (Note [Child lifecycle]): a worker whose socket closed is alive until its
        exit report comes, moments later."""
        return self.proc.poll() is None

    def join(self, timeout: float) -> bool:
        try:
            self.proc.wait(max(0.0, timeout))
            return True
        except subprocess.TimeoutExpired:
            return False

    def drain(self) -> None:
        """Read any READY / error messages waiting on the socket."""
        try:
            while not self.eof and self.conn.poll():
                msg = self.conn.recv()
                if isinstance(msg, Ready):
                    self.ready = True
                elif isinstance(msg, Failed):
                    self.error = msg.text
        except (EOFError, OSError):
            self.eof = True

    def close(self) -> None:
        if not self.conn.closed:
            release_parent_end(self.conn.fileno())
        with contextlib.suppress(OSError):
            self.conn.close()


_TERM_GRACE_S = 2.0  # how long stop waits after SIGTERM, and after SIGKILL, for all children together
_ZYGOTE_GRACE_S = 1.0  # how long stop waits for the zygote to leave at EOF (it only has to exit) before SIGTERM
_SPAWNER_GRACE_S = 1.0  # how long stop waits for the spawner thread to end (it has nothing left to do by then)


def _affinity() -> list[int]:
    """The engine's CPU affinity: its main thread's (the process's, as ``taskset -p`` sets it), not the calling
    thread's, which kept what it had when it was started."""
    try:
        return sorted(os.sched_getaffinity(os.getpid()))
    except OSError:  # the main thread has ended
        return sorted(os.sched_getaffinity(0))


def _join_all(children: list[_Child], timeout: float) -> None:
    deadline = time.monotonic() + timeout
    for ch in children:
        ch.join(deadline - time.monotonic())


class ProcessRunner(Runner):
    def __init__(self, *args, env_for: Callable[[EngineConfig, str], dict[str, str]] | None = None, **kw) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*args, **kw)
        self._env_for = env_for or (lambda cfg, name: {})
        self._children: dict[str, _Child] = {}
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)  # a full pipe already wakes the monitor: never block a writer on it
        self._wake_lock = threading.Lock()  # the zygote's reader wakes us until stop closes the pipe
        self._spawner = _Spawner()
        self._zygote: Zygote | None = None  # the one new workers are forked from
        self._retired: list[Zygote] = []  # older ones, still the parents of workers they forked
        self._owner = os.getpid()  # Note [Child lifecycle]: a fork of the engine stops nothing
        self._retired_children: list[_Child] = []  # workers of heads removed, their sockets still open
        self._retired_closed = threading.Condition(self._lock)  # the monitor closed the sockets of those

    def _wake(self) -> None:
        with self._wake_lock:
            if self._wake_w >= 0:
                with contextlib.suppress(BlockingIOError):
                    os.write(self._wake_w, b"x")

    def _live_zygote(self, env: dict[str, str]) -> Zygote:
        """The zygote to fork a worker with ``env`` from: a new one if there is none yet, the last one died (its
        workers with it), or ``env`` changes a variable its libraries read as they loaded (then the old one stays,
        the parent of the workers it forked, until none is left)."""
        old = self._zygote
        if old is not None and not old.alive():
            log.warning("the worker zygote (pid %d) is gone: starting a new one", old.pid)
            old.close(0.0)
            self._zygote = None
        elif old is not None and (changed := old.stale(env)):
            log.info("%s changed since the worker zygote started: workers are forked from a new one", changed)
            self._retired.append(old)
            self._zygote = None
        for z in [z for z in self._retired if z.idle()]:
            self._retired.remove(z)
            z.close(_ZYGOTE_GRACE_S)
        if self._zygote is None:
            self._zygote = Zygote(
                self._spawner.call, self.cfg.runtime.ready_timeout_s, self._wake, lambda: self._stopping
            )
        return self._zygote

    def _members(self, name: str) -> tuple[str, ...]:
        """The models that share ``name``'s process, in the engine's order (Note [Process groups])."""
        # the runner's config keeps heads removed or failed at run time; they ran alone (add and remove refuse a
        # shared process), but only the models it runs are members
        return tuple(n for n in self.cfg.process_mates(name) if n in self.specs)

    def _launch(self, name: str) -> None:
        names = self._members(name)
        assert names[0] == name, f"{name}'s process is launched through {names[0]}, the first of {names}"
        if self._monitor is not None:  # a restart (the first's counted by the supervisor): the others' too
            for other in names[1:]:
                self.control.add(other, "restarts")
        fds: list[int] = []
        exported: dict[str, RingDesc] = {}  # a mailbox two of them share goes once (the child maps it once)

        def export(ring: str) -> RingDesc:
            if ring not in exported:
                exported[ring] = self.rings[ring].export(fds)
            return exported[ring]

        control = self.control.export(fds)
        specs = [
            replace(s, in_ring=export(s.in_ring.name), out_ring=export(s.out_ring.name), control=control)
            for s in (self.specs[n] for n in names)
        ]
        # the worker's own config: a head added at run time is not in the one the engine started with
        envs = [self._env_for(EngineConfig.model_validate(s.config), s.name) for s in specs]
        env = {**os.environ, **envs[0]}
        priorities = [e["CUDA_MPS_CLIENT_PRIORITY"] for e in envs if "CUDA_MPS_CLIENT_PRIORITY" in e]
        if priorities:  # MPS has one client priority a process: its most important model's ("0" normal, "1" below)
            env["CUDA_MPS_CLIENT_PRIORITY"] = min(priorities)
        proc, conn = start_with_socket(
            lambda theirs: self._live_zygote(env).fork(env, worker_path(), os.getcwd(), _affinity(), theirs)
        )
        _pid, uid = peer_uid(conn.fileno())
        if uid != os.getuid():  # pragma: no cover - we created the socketpair ourselves
            proc.kill()
            raise PermissionError(f"worker {name}: socket peer has uid {uid}")
        conn.send(
            Init(
                specs[0],
                self.cfg.logging.level,
                self.cfg.logging.file,
                more=tuple(specs[1:]),
                # its terminal shows what ours does (the CLI's -v); logging.level is the file's
                terminal_level=logging.getLogger().getEffectiveLevel(),
            )
        )
        send_fds(conn, fds)
        child = _Child(proc, conn, names)
        for n in names:
            self._children[n] = child
        self._wake()

    def _processes(self) -> list[_Child]:
        """Every worker process once (the models of a group share one)."""
        return list({id(ch): ch for ch in self._children.values()}.values())

    def threads_alive(self) -> list[threading.Thread]:
        return [self._monitor] if self._monitor is not None and self._monitor.is_alive() else []

    # ------------------------------------------------------------------------------------------- start
    def start(self) -> None:
        for name in self.specs:
            if name not in self._children:  # the first of a group starts its process
                self._launch(name)
        waiting = self._processes()
        waited = StartWait(self.control, list(self.specs), self.cfg.runtime.ready_timeout_s, "starting")
        errors: list[str] = []
        while waiting:
            remaining = waited.remaining([n for ch in waiting for n in ch.names])  # Note [Start progress]
            if remaining <= 0:
                self._not_ready({n for ch in waiting for n in ch.names})
            objs: list[Any] = [self._wake_r, *(ch.conn for ch in waiting if not ch.eof)]
            if self._wake_r in wait(objs, timeout=min(remaining, POLL_S)):
                os.read(self._wake_r, 4096)
            for ch in list(waiting):
                ch.drain()
                if ch.ready:
                    waiting.remove(ch)
                elif ch.error is not None:
                    errors.append(ch.error)
                    waiting.remove(ch)
                elif not ch.alive():
                    errors.append(f"{'+'.join(ch.names)} exited with code {ch.proc.returncode} before it was ready")
                    waiting.remove(ch)
        self._started(errors)

    # ----------------------------------------------------------------------------------------- monitor
    def _close_retired(self) -> None:
        with self._lock:
            for ch in self._retired_children:
                ch.close()
            self._retired_children.clear()
            self._retired_closed.notify_all()

    def _watched(self) -> list[_Child]:
        """The worker processes to watch: not dead and handled already."""
        return [ch for ch in self._processes() if not ch.handled and not all(n in self._pending for n in ch.names)]

    def _watch(self) -> None:
        while not self._stopping:
            self._close_retired()
            timeout = min(self._run_due_restarts(), POLL_S)
            objs: list[Any] = [self._wake_r]
            with self._lock:
                for ch in self._watched():
                    if not ch.eof:
                        objs.append(ch.conn)
                    if ch.proc.pidfd is not None:  # a death the zygote does not report wakes us too
                        objs.append(ch.proc.pidfd)
            if self._wake_r in wait(objs, timeout=max(0.01, timeout)):
                with contextlib.suppress(OSError):
                    os.read(self._wake_r, 4096)
            with self._lock:
                if self._stopping:
                    return
                for ch in self._watched():
                    was_ready = ch.ready
                    ch.drain()
                    first = ch.names[0]
                    if first in self._adding:  # a head added at run time (alone): add() hears how its start went
                        if ch.ready:
                            self._added(first, None)
                        elif ch.error is not None or not ch.alive():
                            ch.handled = True
                            self._added(first, ch.error or f"{first} exited with code {ch.proc.returncode}")
                        continue
                    if ch.ready and not was_ready:
                        log.info("%s is ready again (pid %d)", "+".join(ch.names), ch.proc.pid)
                    if ch.alive():
                        continue  # gone without a report yet: poll() gives the zygote REPORT_GRACE_S to send one
                    reason = describe_exit(ch.proc.returncode)
                    if ch.error:
                        reason += ": " + ch.error.strip().splitlines()[-1]
                    # its own report (a worker's loop that raised) is in its last_error already, whole
                    reported = ch.error is not None and not ch.killed
                    ch.close()
                    ch.handled = True
                    # a worker leaves by itself only at stop: any exit now is a crash, exit code 0 included
                    self._on_process_exit(ch.names, reason, reported)
            self._check_hangs()

    def _on_process_exit(self, names: tuple[str, ...], reason: str, reported: bool = False) -> None:
        """A worker process is gone, and every model it ran (Note [Process groups]): each is cleaned up after and
        counted a crash; the first decides for all whether and when they restart (one process, one decision).
        ``reported``: the first model's worker wrote why into its last_error before it left."""
        for name in names[1:]:
            self._cleanup_after(name)
        self._on_first_exit(names, reason, reported)

    def _launch_failed(self, name: str, reason: str) -> None:
        """A restart could not launch ``name``'s process: a crash of every model it runs, decided by the first."""
        self._on_first_exit(self._members(name), reason)

    def _on_first_exit(self, names: tuple[str, ...], reason: str, reported: bool = False) -> None:
        first, others = names[0], names[1:]
        if not self._stopping:
            # stats()' last_error says why (a hang, a signal, an exit), unless the worker's own report is there
            for name in others if reported else names:
                self.control.set_error(name, f"{first}'s process stopped: {reason}")
            for name in others:
                self.control.add(name, "crashes")
        self._on_exit(first, crashed=True, reason=reason)
        for name in others:  # restarting again, or failed for good: as the first is
            self.control.set(name, "state", self.control.get(first, "state"))

    def _check_hangs(self) -> None:
        limit = self.cfg.runtime.hang_timeout_s
        if limit is None:
            return
        now = time.monotonic()
        with self._lock:
            for ch in self._watched():
                if not ch.ready or ch.killed or not ch.alive():
                    continue
                for name in ch.names:
                    hb = self.control.get(name, "heartbeat")
                    if hb > 0 and now - hb > limit:
                        log.error(
                            "%s has not reported for %.0f s (runtime.hang_timeout_s); killing its process%s",
                            name,
                            now - hb,
                            f" (and {', '.join(n for n in ch.names if n != name)} with it)"
                            if len(ch.names) > 1
                            else "",
                        )
                        ch.error = f"{name} hung for {now - hb:.0f} s"
                        ch.killed = True
                        ch.proc.kill()
                        break

    def _retire(self, name: str) -> list[threading.Thread]:
        with self._lock:
            ch = self._children.get(name)
            if ch is None:
                return []
            assert ch.names == (name,), f"{name} shares its process with {ch.names}: removed only with them"
            del self._children[name]
        with contextlib.suppress(OSError, ValueError):
            ch.conn.send(Stop())
        for ring in list(self.rings.values()):  # a head added or removed meanwhile changes the dict
            ring.wake_all()
        _join_all([ch], self.cfg.runtime.stop_timeout_s)
        for end in (ch.proc.terminate, ch.proc.kill):
            if ch.alive():
                end()
                _join_all([ch], _TERM_GRACE_S)
        with self._lock:  # the monitor may be polling its socket now: it closes it once it is not
            self._retired_children.append(ch)
        self._wake()
        monitor = self._monitor
        if monitor is not None and monitor.is_alive() and threading.current_thread() is not monitor:
            with self._lock:  # the caller gets back a runner with nothing of the head's left open
                closed = self._retired_closed.wait_for(
                    lambda: ch not in self._retired_children or self._stopping, self.cfg.runtime.stop_timeout_s
                )
            if not closed:
                log.warning(
                    "%s: the monitor did not close its worker's socket within %.1f s; it will at its next look",
                    name,
                    self.cfg.runtime.stop_timeout_s,
                )
        return []

    # -------------------------------------------------------------------------------------------- stop
    def stop(self) -> list[str]:
        if os.getpid() != self._owner:  # Note [Child lifecycle]: a fork's copy drops its references, nothing more
            self._children, self._zygote, self._retired = {}, None, []
            return []
        self._stopping = True  # before the lock: a launch waiting on the zygote, lock held, gives up
        self._abandon_adds()
        with self._lock:
            self._pending.clear()
            self._retired_closed.notify_all()  # a removal waiting for its socket's close waits no more
        with contextlib.suppress(OSError):
            self._wake()
        self.control.request_stop()
        for ring in list(self.rings.values()):  # a head added or removed meanwhile changes the dict
            ring.wake_all()
        children = [(ch.names, ch) for ch in self._processes()]
        for _, ch in children:
            with contextlib.suppress(OSError, ValueError):
                ch.conn.send(Stop())
        # Each phase waits for all children at once, against one deadline: nine hung workers take one grace time,
        # not nine.
        _join_all([ch for _, ch in children], self.cfg.runtime.stop_timeout_s)
        forced = [name for names, ch in children if ch.alive() for name in names]
        for _, ch in children:
            if ch.alive():
                ch.proc.terminate()
        _join_all([ch for _, ch in children if ch.alive()], _TERM_GRACE_S)
        for _, ch in children:
            if ch.alive():
                ch.proc.kill()  # works on a stopped (SIGSTOP) process too
        _join_all([ch for _, ch in children if ch.alive()], _TERM_GRACE_S)
        for names, ch in children:
            for name in names:
                self.control.set_state(name, STOPPED)
            ch.close()
        if self._monitor is not None and self._monitor is not threading.current_thread():
            self._monitor.join(2.0)
        self._close_retired()
        for z in [*self._retired, *([self._zygote] if self._zygote else [])]:
            z.close(_ZYGOTE_GRACE_S)  # after the workers: its end would SIGKILL those still there
        self._spawner.close(_SPAWNER_GRACE_S)
        with self._wake_lock:
            for fd in (self._wake_r, self._wake_w):
                with contextlib.suppress(OSError):
                    os.close(fd)
            self._wake_r = self._wake_w = -1
        if forced:
            log.warning(
                "workers %s did not stop within %.1f s and were terminated",
                forced,
                self.cfg.runtime.stop_timeout_s,
            )
        return forced
