"""The zygote: one interpreter that imports what every worker needs, once, and forks the workers of an engine.

See Note [Child lifecycle] in process.py for why a fork is safe here and how parent death propagates. Two faces:
``main`` runs in the zygote process; ``Zygote`` and ``WorkerProc`` are the engine's handles on it and on a worker.
Top-level imports stay light: ``main`` asks for its parent-death signal before anything slow is imported.
"""

from __future__ import annotations

import contextlib
import gc
import importlib
import logging
import os
import queue
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from vpengine.runtime.child import die_with_parent
from vpengine.runtime.sockets import hold_parent_end, recv_fds, release_parent_end, send_fds

log = logging.getLogger("vpengine.zygote")

#: What every worker imports: the zygote imports it once, and its forks find it loaded.
PRELOAD = (
    "torch",
    "vpengine.runtime.worker",
    "vpengine.runtime.child",
    "vpengine.runtime.process",
    "vpengine.runtime.control",
    "vpengine.transport.ring",
    "vpengine.models.base",
)
#: How long a start request may wait for the zygote's answer (a fork, even of a big process, takes milliseconds).
REPLY_TIMEOUT_S = 30.0
#: How long the workers of a zygote that died get to go (the kernel SIGKILLs them) before they are killed here.
_ORPHAN_GRACE_S = 2.0


# ----------------------------------------------------------------------------------- messages on the socket
@dataclass(frozen=True)
class Fork:
    """Engine -> zygote: start a worker; its end of its socketpair follows by SCM_RIGHTS."""

    env: dict[str, str]
    path: list[str]
    cwd: str


@dataclass(frozen=True)
class Forked:
    """Zygote -> engine: the answer to a ``Fork``, or the zygote is up (its own pid) once preloaded."""

    pid: int


@dataclass(frozen=True)
class ZygoteError:
    """Zygote -> engine: the preload or a fork failed; the text says why."""

    text: str


@dataclass(frozen=True)
class Exited:
    """Zygote -> engine: a worker it forked is gone and reaped; ``returncode`` as ``subprocess.Popen`` has it."""

    pid: int
    returncode: int


# --------------------------------------------------------------------------------------- the zygote itself
_BOOT = (
    "import sys; base = list(sys.path); sys.path[:0] = sys.argv[3:]; del sys.argv[3:]; "
    "from vpengine.runtime.zygote import main; main(int(sys.argv[1]), int(sys.argv[2]), base)"
)


def worker_path() -> list[str]:
    """A worker's import path, before the isolated interpreter's own: this package's folder, then the engine's
    ``sys.path`` made absolute (as the engine resolves it now); never its cwd (Note [Child lifecycle])."""
    src = str(Path(__file__).resolve().parents[2])
    return [*dict.fromkeys([src, *(os.path.abspath(p) for p in sys.path)])]


def zygote_command(fd: int) -> list[str]:
    """The command line of a zygote that talks over socket ``fd``: isolated (-I), with ``worker_path()``."""
    return [sys.executable, "-I", "-c", _BOOT, str(fd), str(os.getpid()), *worker_path()]


def main(fd: int, parent_pid: int, base_path: list[str]) -> None:
    """The zygote's entry: preload, say so, then fork a worker per request and report each one's exit, until the
    engine's end of the socket closes."""
    die_with_parent(parent_pid)
    conn = Connection(fd)
    try:
        for name in PRELOAD:
            importlib.import_module(name)
    except BaseException:
        conn.send(ZygoteError(traceback.format_exc()))
        os._exit(3)
    # SIGCHLD only writes a byte to a pipe the loop selects on: the zygote never runs code in a signal handler
    wake_r, wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    signal.set_wakeup_fd(wake_w, warn_on_full_buffer=False)
    gc.freeze()  # what the preload made stays put: its pages stay shared with every fork (copy-on-write)
    conn.send(Forked(os.getpid()))
    try:
        while True:
            readable, _, _ = select.select([fd, wake_r], [], [])
            if wake_r in readable:
                with contextlib.suppress(BlockingIOError):
                    os.read(wake_r, 4096)
            _reap(conn)
            if fd in readable:
                try:
                    request = conn.recv()
                    fds = recv_fds(conn)
                except (EOFError, OSError):
                    break  # the engine closed its end, or died
                try:
                    reply: Forked | ZygoteError = Forked(_fork(request, fds[0], base_path, conn, (wake_r, wake_w)))
                except Exception as e:
                    reply = ZygoteError(f"could not fork a worker: {type(e).__name__}: {e}")
                finally:
                    for f in fds:
                        os.close(f)
                conn.send(reply)
    except (EOFError, OSError):
        pass  # the engine is gone: our workers go with us (their parent-death signal)
    os._exit(0)


def _reap(conn: Connection) -> None:
    while True:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        conn.send(Exited(pid, os.waitstatus_to_exitcode(status)))


def _fork(request: Fork, fd: int, base_path: list[str], conn: Connection, wake: tuple[int, int]) -> int:
    if sys.modules["torch"].cuda.is_initialized():  # Note [Child lifecycle]: a forked CUDA context is unusable
        raise RuntimeError("the zygote has initialised CUDA; it must never do that")
    with warnings.catch_warnings():
        # Python 3.12+ warns about fork with other threads alive. The only other thread is OpenBLAS's pool
        # (numpy starts it at import); OpenBLAS shuts it down around fork itself (pthread_atfork).
        warnings.simplefilter("ignore", DeprecationWarning)
        zygote_pid = os.getpid()  # taken before the fork: after it, getppid() would already name a new parent
        pid = os.fork()
    if pid:
        return pid
    code = 1
    try:
        os.setsid()  # a session of its own, as a worker started by the engine had
        signal.set_wakeup_fd(-1)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        for f in wake:
            os.close(f)
        conn.close()  # the worker holds one descriptor: its own socket
        os.environ.clear()
        os.environ.update(request.env)  # putenv too: CUDA, initialised later, reads the MPS variables from there
        sys.path[:] = [*request.path, *base_path]
        os.chdir(request.cwd)
        from vpengine.runtime.child import main as worker_main

        worker_main(fd, zygote_pid)
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    except BaseException:
        traceback.print_exc()
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)  # never back into the zygote's loop


# ---------------------------------------------------------------------------------------- the engine's side
class WorkerProc:
    """A worker the zygote forked: the part of ``subprocess.Popen`` the runner uses. Its exit code comes from the
    zygote's report (only a parent can reap); signals go through a pidfd opened as soon as its pid was known, so a
    signal never reaches another process that got the pid later."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.returncode: int | None = None
        self._cond = threading.Condition()
        try:
            self._pidfd: int | None = os.pidfd_open(pid)
        except (AttributeError, OSError):  # kernel < 5.3, or gone already (its report is on its way)
            self._pidfd = None

    def poll(self) -> int | None:
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        with self._cond:
            if not self._cond.wait_for(lambda: self.returncode is not None, timeout):
                raise subprocess.TimeoutExpired(f"worker pid {self.pid}", timeout or 0.0)
            assert self.returncode is not None
            return self.returncode

    def send_signal(self, sig: int) -> None:
        with self._cond:
            if self.returncode is not None:
                return
            with contextlib.suppress(ProcessLookupError):
                if self._pidfd is not None:
                    signal.pidfd_send_signal(self._pidfd, sig)
                else:
                    os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def _gone(self) -> bool:
        """Exited (a zombie counts), whether or not it has been reaped yet."""
        if self._pidfd is not None:
            return bool(select.select([self._pidfd], [], [], 0)[0])
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:  # pragma: no cover - the pid went to someone else's process
            return True
        return False

    def _exited(self, code: int) -> None:
        with self._cond:
            self.returncode = code
            if self._pidfd is not None:
                os.close(self._pidfd)
                self._pidfd = None
            self._cond.notify_all()


class Zygote:
    """The engine's handle on its zygote. ``spawn`` runs a callable on the runner's spawner thread (the zygote's
    parent-death signal is tied to that thread); ``notify`` is called from the reader thread after each exit report;
    ``abort`` ends a wait early (the runner is stopping)."""

    def __init__(
        self,
        spawn: Callable[[Callable[[], Any]], Any],
        timeout: float,
        notify: Callable[[], None],
        abort: Callable[[], bool],
    ) -> None:
        self._notify, self._abort = notify, abort
        self._procs: dict[int, WorkerProc] = {}
        self._replies: queue.SimpleQueue[WorkerProc | ZygoteError | None] = queue.SimpleQueue()
        self._lock = threading.Lock()  # one start request at a time
        self._lost = threading.Event()
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        hold_parent_end(ours.fileno())
        self._fd = ours.fileno()
        try:
            self.proc: subprocess.Popen[bytes] = spawn(
                lambda: subprocess.Popen(
                    zygote_command(theirs.fileno()), pass_fds=[theirs.fileno()], start_new_session=True
                )
            )
        except BaseException:
            release_parent_end(ours.fileno())
            ours.close()
            raise
        finally:
            theirs.close()
        self._conn = Connection(ours.detach())
        try:
            first = self._first_message(timeout)
        except BaseException:
            self.close(0.0)
            raise
        self.pid = first.pid
        self._reader = threading.Thread(target=self._read, name="vpengine-zygote", daemon=True)
        self._reader.start()

    def _first_message(self, timeout: float) -> Forked:
        from vpengine.runtime.supervisor import EngineStartError

        deadline = time.monotonic() + timeout
        while not self._conn.poll(0.2):  # slices, so that a stop need not wait out a slow import
            if self._abort():
                raise RuntimeError("the engine is stopping: no worker is started any more")
            if time.monotonic() > deadline:
                raise EngineStartError(f"the worker zygote was not ready within {timeout} s (runtime.ready_timeout_s)")
        try:
            msg = self._conn.recv()
        except (EOFError, OSError):
            code = self.proc.wait()
            raise EngineStartError(f"the worker zygote exited with code {code} before it was ready") from None
        if isinstance(msg, ZygoteError):
            raise EngineStartError("the worker zygote could not preload:\n" + msg.text)
        assert isinstance(msg, Forked), msg
        return msg

    def alive(self) -> bool:
        return not self._lost.is_set()

    def fork(self, env: dict[str, str], path: list[str], cwd: str, fd: int) -> WorkerProc:
        """Start a worker with this environment, import path and working directory, talking over socket ``fd``."""
        with self._lock:
            if self._lost.is_set():
                raise RuntimeError(f"the worker zygote (pid {self.pid}) is gone")
            self._conn.send(Fork(env, path, cwd))
            send_fds(self._conn, [fd])
            deadline = time.monotonic() + REPLY_TIMEOUT_S
            while True:
                try:
                    reply = self._replies.get(timeout=0.2)
                    break
                except queue.Empty:
                    if self._abort():
                        raise RuntimeError("the engine is stopping: no worker is started any more") from None
                    if time.monotonic() > deadline:  # stuck (stopped?): start afresh with a new one
                        self._lost.set()  # before its late answer could be taken for the next request's
                        self.proc.kill()
                        raise RuntimeError(
                            f"the worker zygote (pid {self.pid}) did not answer a start request "
                            f"within {REPLY_TIMEOUT_S} s; killed it"
                        ) from None
        if reply is None:
            raise RuntimeError(f"the worker zygote (pid {self.pid}) is gone")
        if isinstance(reply, ZygoteError):
            raise RuntimeError(reply.text)
        return reply

    def _read(self) -> None:
        try:
            while True:
                msg = self._conn.recv()
                if isinstance(msg, Exited):
                    proc = self._procs.pop(msg.pid, None)
                    if proc is not None:
                        proc._exited(msg.returncode)
                        self._notify()
                elif isinstance(msg, Forked):
                    # registered before the next message is read: this worker's exit report comes after it
                    self._procs[msg.pid] = WorkerProc(msg.pid)
                    self._replies.put(self._procs[msg.pid])
                elif isinstance(msg, ZygoteError):
                    self._replies.put(msg)
        except (EOFError, OSError):
            pass
        except Exception:  # a message we cannot read: treat the zygote as lost rather than wait on it for ever
            log.exception("reading from the worker zygote (pid %d) failed; starting afresh", self.pid)
            with contextlib.suppress(OSError):
                self.proc.kill()
        self._lost.set()
        self._replies.put(None)
        self._bury(list(self._procs.values()))
        self._procs.clear()
        self._notify()

    @staticmethod
    def _bury(procs: list[WorkerProc]) -> None:
        """The zygote is gone, and the kernel SIGKILLs its workers (their parent-death signal); nobody reports
        their exits now. Wait until they are gone (a bounded time, then kill), and report each as killed by
        SIGKILL: a worker that exited by itself just before the zygote died is reported so too."""
        deadline = time.monotonic() + _ORPHAN_GRACE_S
        while any(not p._gone() for p in procs) and time.monotonic() < deadline:
            time.sleep(0.02)
        for p in procs:
            if not p._gone():
                p.kill()
            p._exited(-signal.SIGKILL)

    def close(self, timeout: float) -> None:
        """End the zygote (EOF on its socket; then SIGTERM, then SIGKILL) and wait for it, bounded. Its workers
        should be gone already: any left die with it."""
        with contextlib.suppress(OSError):
            sock = socket.socket(fileno=os.dup(self._conn.fileno()))
            try:
                sock.shutdown(socket.SHUT_RDWR)  # the zygote reads EOF and leaves; our reader wakes with EOF
            finally:
                sock.close()
        for step, grace in ((None, timeout), (self.proc.terminate, 0.5), (self.proc.kill, 2.0)):
            if step is not None:
                step()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(grace)
                break
        reader = getattr(self, "_reader", None)
        if reader is not None and reader is not threading.current_thread():
            reader.join(_ORPHAN_GRACE_S + 2.0)
        release_parent_end(self._fd)
        with contextlib.suppress(OSError):
            self._conn.close()
