"""The zygote: one interpreter that imports what every worker needs, once, and forks the workers of an engine.

See Note [Child lifecycle] in process.py for why a fork is safe here and how parent death propagates. This module is
what runs in the zygote (``main``) and the messages it exchanges with the engine; the engine's handles on the zygote
and on a worker are in zygote_handle.py. Top-level imports stay light: ``main`` asks for its parent-death signal
before anything slow is imported.
"""

from __future__ import annotations

import contextlib
import gc
import importlib
import os
import select
import signal
import sys
import traceback
import warnings
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path

from vpengine.runtime.child import die_with_parent
from vpengine.runtime.sockets import recv_fds, send_fds

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
#: Variables read once, when a library loads (the dynamic linker, OpenMP, OpenBLAS, MKL, torch's logging): a fork
#: inherits what the zygote read at its start, whatever its environment says later. When one of them differs in a
#: start request, the engine starts a new zygote first (Note [Child lifecycle]).
LOAD_TIME_ENV = (
    "LD_PRELOAD",
    "LD_LIBRARY_PATH",
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "TORCH_LOGS",
)


# ----------------------------------------------------------------------------------- messages on the socket
@dataclass(frozen=True)
class Fork:
    """Engine -> zygote: start a worker; its end of its socketpair follows by SCM_RIGHTS. ``affinity`` is the
    engine's CPU affinity at this (re)start, which the worker takes over."""

    env: dict[str, str]
    path: list[str]
    cwd: str
    affinity: list[int]


@dataclass(frozen=True)
class Forked:
    """Zygote -> engine: the answer to a ``Fork``, and then a pidfd of the worker by SCM_RIGHTS (no descriptor
    where the kernel has no pidfd); or, first of all and with nothing after it, the zygote is up (its own pid)."""

    pid: int


@dataclass(frozen=True)
class Kill:
    """Engine -> zygote, for a worker of which the engine has no pidfd: signal it, unless it is reaped already
    (only then could its pid belong to another process)."""

    pid: int
    sig: int


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
    live: set[int] = set()  # forked and not reaped: the only pids a Kill may signal
    try:
        while True:
            readable, _, _ = select.select([fd, wake_r], [], [])
            if wake_r in readable:
                with contextlib.suppress(BlockingIOError):
                    os.read(wake_r, 4096)
            _reap(conn, live)
            if fd in readable:
                try:
                    request = conn.recv()
                    fds = recv_fds(conn) if isinstance(request, Fork) else []
                except (EOFError, OSError):
                    break  # the engine closed its end, or died
                if isinstance(request, Kill):
                    if request.pid in live:  # not reaped: the pid is still its (a zombie holds it)
                        with contextlib.suppress(OSError):
                            os.kill(request.pid, request.sig)
                    continue
                pidfd: int | None = None
                try:
                    pid, pidfd = _fork(request, fds[0], base_path, conn, (wake_r, wake_w))
                    live.add(pid)
                    reply: Forked | ZygoteError = Forked(pid)
                except Exception as e:
                    reply = ZygoteError(f"could not fork a worker: {type(e).__name__}: {e}")
                finally:
                    for f in fds:
                        os.close(f)
                conn.send(reply)
                if isinstance(reply, Forked):  # reaped only after this, so the pidfd names this worker
                    send_fds(conn, [pidfd] if pidfd is not None else [])
                if pidfd is not None:
                    os.close(pidfd)
    except (EOFError, OSError):
        pass  # the engine is gone: our workers go with us (their parent-death signal)
    os._exit(0)


def _reap(conn: Connection, live: set[int]) -> None:
    while True:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        live.discard(pid)
        conn.send(Exited(pid, os.waitstatus_to_exitcode(status)))


def _cuda_touched() -> bool:
    """CUDA initialised in this process. torch's own flag: a CUDA build maps libcuda when it is imported (seen on an
    H200), so the library being loaded says nothing; a context exists only once something initialised it."""
    return bool(sys.modules["torch"].cuda.is_initialized())


def exit_status(code: object) -> int:
    """The exit status of ``SystemExit(code)``, as the interpreter has it: None is 0, an int itself, anything else
    is printed to stderr and is 1."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    with contextlib.suppress(Exception):
        print(code, file=sys.stderr)
    return 1


def _fork(
    request: Fork, fd: int, base_path: list[str], conn: Connection, wake: tuple[int, int]
) -> tuple[int, int | None]:
    if _cuda_touched():  # Note [Child lifecycle]: a forked CUDA context is unusable
        raise RuntimeError("the zygote has initialised CUDA; it must never do that")
    with warnings.catch_warnings():
        # Python 3.12+ warns about fork with other threads alive: OpenBLAS's pool (numpy starts it at import) is
        # the only other thread, and OpenBLAS quiesces it around fork itself (pthread_atfork).
        warnings.simplefilter("ignore", DeprecationWarning)
        zygote_pid = os.getpid()  # taken before the fork: after it, getppid() would already name a new parent
        pid = os.fork()
    if pid:
        try:  # before the loop can reap it: until then the pid cannot name another process
            pidfd: int | None = os.pidfd_open(pid)
        except (AttributeError, OSError):  # kernel < 5.3: the engine signals it through us (``Kill``)
            pidfd = None
        return pid, pidfd
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
        with contextlib.suppress(OSError):  # CPUs a cgroup no longer grants: the zygote's affinity stands
            os.sched_setaffinity(0, request.affinity)
        sys.path[:] = [*request.path, *base_path]
        importlib.invalidate_caches()  # the finders' directory listings are the zygote's, maybe long out of date
        os.chdir(request.cwd)
        from vpengine.runtime.child import main as worker_main

        worker_main(fd, zygote_pid)
        code = 0
    except SystemExit as e:
        code = exit_status(e.code)
    except BaseException:
        traceback.print_exc()
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)  # never back into the zygote's loop
