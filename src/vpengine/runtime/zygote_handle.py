"""The engine's side of the zygote (runtime/zygote.py, Note [Child lifecycle] in process.py): ``Zygote``, its handle
on the zygote process, and ``WorkerProc``, its handle on one worker the zygote forked."""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import select
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from typing import Any

from vpengine.runtime.sockets import recv_fds, release_parent_end, send_fds, start_with_socket
from vpengine.runtime.zygote import LOAD_TIME_ENV, Exited, Fork, Forked, Kill, ZygoteError, zygote_command

log = logging.getLogger("vpengine.zygote")

#: How long a start request may wait for the zygote's answer (a fork, even of a big process, takes milliseconds).
REPLY_TIMEOUT_S = 30.0
#: How long the workers of a zygote that died get to go (the kernel SIGKILLs them) before they are killed here.
_ORPHAN_GRACE_S = 2.0
#: How long a worker may be gone (its pidfd says so) without the zygote's report before the zygote counts as lost:
#: a zygote that reaps reports within milliseconds; one that does not is stopped (SIGSTOP) or stuck.
REPORT_GRACE_S = 1.0
#: The ``returncode`` of a worker whose exit status nobody can know: it died while its zygote was not reaping.
#: Outside any real status (0..255, or minus a signal number).
EXIT_UNKNOWN = 256


def describe_exit(code: int | None) -> str:
    """A worker's ``returncode`` in words, for logs and ``stats()``."""
    if code == EXIT_UNKNOWN:
        return "exit code unknown (its zygote was not reaping)"
    return f"exit code {code}" if code is None or code >= 0 else f"killed by signal {-code}"


class WorkerProc:
    """A worker the zygote forked: the part of ``subprocess.Popen`` the runner uses. Its exit code comes from the
    zygote's report (only a parent can reap). Its pidfd, which the zygote opened before it could reap the worker
    and so names this very process, carries its signals and tells whether it is gone; a worker gone for
    ``REPORT_GRACE_S`` with no report means the zygote is lost (``lost`` is called). Without a pidfd (kernel < 5.3)
    signals go through the zygote (``via_zygote``), which signals only children it has not reaped: a bare pid is
    never signalled here."""

    def __init__(
        self,
        pid: int,
        pidfd: int | None,
        via_zygote: Callable[[int, int], None],
        lost: Callable[[], None],
        owner: int,
    ) -> None:
        self.pid = pid
        self.returncode: int | None = None
        self._cond = threading.Condition()
        self._pidfd = pidfd
        self._via_zygote, self._lost, self._owner = via_zygote, lost, owner
        self.exit_seen: float | None = None  # when its pidfd first said it was gone and no report had come

    @property
    def pidfd(self) -> int | None:
        """A descriptor that becomes readable when the worker exits, for a monitor to wait on; None when there is
        none, or once it has been seen readable (it would wake the monitor at once, for ever)."""
        return self._pidfd if self.exit_seen is None else None

    def poll(self) -> int | None:
        with self._cond:
            if self.returncode is not None or self._pidfd is None:
                return self.returncode
            if self.exit_seen is None and select.select([self._pidfd], [], [], 0)[0]:
                self.exit_seen = time.monotonic()
            overdue = self.exit_seen is not None and time.monotonic() - self.exit_seen > REPORT_GRACE_S
        if overdue:
            self._lost()  # outside the lock: the zygote's reader takes it to report the exits
        return None

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:  # in slices: poll notices a worker gone without a report
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise subprocess.TimeoutExpired(f"worker pid {self.pid}", timeout or 0.0)
            with self._cond:
                self._cond.wait_for(lambda: self.returncode is not None, 0.25 if left is None else min(left, 0.25))
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if os.getpid() != self._owner:  # a copy in a process forked from the engine: not its worker to signal
            return
        with self._cond:
            if self.returncode is not None:
                return
            if self._pidfd is not None:
                with contextlib.suppress(ProcessLookupError):
                    signal.pidfd_send_signal(self._pidfd, sig)
                return
        self._via_zygote(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def _gone(self) -> bool:
        """Exited (a zombie counts), whether or not it has been reaped; without a pidfd nothing can tell, and the
        kernel's parent-death SIGKILL is taken at its word."""
        with self._cond:
            return self._pidfd is None or bool(select.select([self._pidfd], [], [], 0)[0])

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
    ``abort`` ends a wait early (the runner is stopping). In a process forked from the engine, the copy of the handle
    sends nothing and signals nothing (Note [Child lifecycle])."""

    def __init__(
        self,
        spawn: Callable[[Callable[[], Any]], Any],
        timeout: float,
        notify: Callable[[], None],
        abort: Callable[[], bool],
    ) -> None:
        self.owner = os.getpid()
        self._notify, self._abort = notify, abort
        self._procs: dict[int, WorkerProc] = {}
        self._replies: queue.SimpleQueue[WorkerProc | ZygoteError | None] = queue.SimpleQueue()
        self._lock = threading.Lock()  # one start request at a time
        self._send_lock = threading.Lock()  # a message and the descriptors after it go out together
        self._lost = threading.Event()
        self._killed = False  # declared lost: killed here, its workers' exit status unknown
        self._closed = False
        # what the zygote's libraries read as they load (it inherits this environment)
        self.load_env = {k: os.environ.get(k) for k in LOAD_TIME_ENV}
        self.proc: subprocess.Popen[bytes]
        self.proc, self._conn = start_with_socket(
            lambda theirs: spawn(
                lambda: subprocess.Popen(zygote_command(theirs), pass_fds=[theirs], start_new_session=True)
            )
        )
        self._fd = self._conn.fileno()
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
            try:
                code: int | str = self.proc.wait(_ORPHAN_GRACE_S)
            except subprocess.TimeoutExpired:  # closed its socket but lives on: not ours to wait for
                self.proc.kill()
                code = "unknown (killed)"
            raise EngineStartError(f"the worker zygote exited with code {code} before it was ready") from None
        if isinstance(msg, ZygoteError):
            raise EngineStartError("the worker zygote could not preload:\n" + msg.text)
        assert isinstance(msg, Forked), msg
        return msg

    def alive(self) -> bool:
        return not self._lost.is_set()

    def stale(self, env: dict[str, str]) -> list[str]:
        """The load-time variables (``LOAD_TIME_ENV``) that ``env`` sets otherwise than this zygote read them."""
        return [k for k in LOAD_TIME_ENV if env.get(k) != self.load_env[k]]

    def idle(self) -> bool:
        """No worker of this zygote is left (every exit reported), or it is gone."""
        return not self._procs or self._lost.is_set()

    def fork(self, env: dict[str, str], path: list[str], cwd: str, affinity: list[int], fd: int) -> WorkerProc:
        """Start a worker with this environment, import path, working directory and CPU affinity, talking over
        socket ``fd``."""
        with self._lock:
            if self._lost.is_set():
                raise RuntimeError(f"the worker zygote (pid {self.pid}) is gone")
            with self._send_lock:
                self._conn.send(Fork(env, path, cwd, affinity))
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

    def _signal(self, pid: int, sig: int) -> None:
        """Signal a worker of ours that has no pidfd, through the zygote (``Kill``)."""
        if os.getpid() != self.owner or self._lost.is_set():
            return  # a gone zygote's workers get the kernel's SIGKILL
        with self._send_lock, contextlib.suppress(OSError, ValueError):
            self._conn.send(Kill(pid, sig))

    def declare_lost(self) -> None:
        """A worker is gone and the zygote has not reported it: the zygote is stopped or stuck, and nothing it
        forked would be reported any more. Kill it; its reader then sees EOF and buries its workers."""
        if os.getpid() != self.owner or self._killed or self._lost.is_set():
            return
        self._killed = True
        log.error(
            "the worker zygote (pid %d) did not report a worker's exit within %.0f s; killing it, its workers "
            "are restarted from a new one",
            self.pid,
            REPORT_GRACE_S,
        )
        with contextlib.suppress(OSError):
            self.proc.kill()  # our own child, not reaped yet: the pid is its

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
                    fds = recv_fds(self._conn)
                    for f in fds:  # recvmsg does not set close-on-exec: a program the engine runs must not get it
                        os.set_inheritable(f, False)
                    # registered before the next message is read: this worker's exit report comes after it
                    self._procs[msg.pid] = WorkerProc(
                        msg.pid, fds[0] if fds else None, self._signal, self.declare_lost, self.owner
                    )
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
        self._bury(list(self._procs.values()), self._killed)
        self._procs.clear()
        self._notify()

    @staticmethod
    def _bury(procs: list[WorkerProc], killed: bool) -> None:
        """The zygote is gone, and the kernel SIGKILLs its workers (their parent-death signal); nobody reports
        their exits now. Wait until they are gone (a bounded time, then kill through their pidfds), and report each
        as killed by SIGKILL; one seen gone before a zygote that was not reaping was killed, with status unknown."""
        deadline = time.monotonic() + _ORPHAN_GRACE_S
        while any(not p._gone() for p in procs) and time.monotonic() < deadline:
            time.sleep(0.02)
        for p in procs:
            if not p._gone():
                p.kill()
            p._exited(EXIT_UNKNOWN if killed and p.exit_seen is not None else -signal.SIGKILL)

    def close(self, timeout: float) -> None:
        """End the zygote (EOF on its socket; then SIGTERM, then SIGKILL) and wait for it, bounded: at most
        ``timeout`` + 2.5 s, and then up to 4 s for its reader. Its workers should be gone already: any left die
        with it. Once only; in a process forked from the engine it only drops the handle."""
        if self._closed:
            return
        self._closed = True
        if os.getpid() != self.owner:
            return
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
