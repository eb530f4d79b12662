"""A child's socket (Note [Child lifecycle] in process.py): the messages on it, file descriptors over it with
SCM_RIGHTS, and the engine's ends of such sockets kept out of processes forked from the engine.

Light on purpose (the standard library only): the zygote and workers import it before anything slow.
"""

from __future__ import annotations

import contextlib
import os
import socket
import struct
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    from vpengine.runtime.worker import WorkerSpec


def peer_uid(sock_fd: int) -> tuple[int, int]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM, fileno=os.dup(sock_fd))
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    finally:
        sock.close()
    pid, uid, _gid = struct.unpack("3i", raw)
    return pid, uid


def send_fds(conn: Connection, fds: list[int]) -> None:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM, fileno=os.dup(conn.fileno()))
    try:
        socket.send_fds(sock, [struct.pack("i", len(fds))], fds)
    finally:
        sock.close()


def recv_fds(conn: Connection) -> list[int]:
    _pid, uid = peer_uid(conn.fileno())
    if uid != os.getuid():
        raise PermissionError(f"handle socket peer runs as uid {uid}, not {os.getuid()}; refusing its handles")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM, fileno=os.dup(conn.fileno()))
    try:
        msg, fds, _flags, _addr = socket.recv_fds(sock, 4, 256)
    finally:
        sock.close()
    expected = struct.unpack("i", msg)[0] if len(msg) == 4 else -1
    if len(fds) != expected:
        raise RuntimeError(f"expected {expected} file descriptors from the engine, got {len(fds)}")
    return fds


# ----------------------------------------------------------------------------------- messages on the socket
@dataclass(frozen=True)
class Init:
    """Parent -> worker, first: what to run (the fds of its rings follow, Note [Child lifecycle])."""

    spec: WorkerSpec
    log_level: str  # logging.level: what goes to logging.file
    log_file: str | None
    more: tuple[WorkerSpec, ...] = ()  # the other models of its process (Note [Process groups] in process.py)
    terminal_level: int = 30  # what goes to its stderr (logging's number, WARNING): what the parent's terminal shows


@dataclass(frozen=True)
class Ready:
    """Worker -> parent: loaded, warmed up and serving."""

    pid: int


@dataclass(frozen=True)
class Failed:
    """Worker -> parent: it could not start, or its loop raised; its traceback."""

    text: str


@dataclass(frozen=True)
class Stop:
    """Parent -> worker: leave the loop."""


# Note [Child lifecycle]: the parent's socket ends, replaced by /dev/null in any process forked from the parent
_PARENT_ENDS: set[int] = set()


def hold_parent_end(fd: int) -> None:
    """``fd`` is the engine's end of a socket to a child: a process forked from the engine gets /dev/null there."""
    _PARENT_ENDS.add(fd)


def release_parent_end(fd: int) -> None:
    """``fd`` is about to be closed: forks no longer need it replaced."""
    _PARENT_ENDS.discard(fd)


_T = TypeVar("_T")


def start_with_socket(start: Callable[[int], _T]) -> tuple[_T, Connection]:
    """Call ``start`` with the child's end (a descriptor) of a new UNIX socket pair, to hand to the process it
    starts; return what it returns and the engine's end, held for forks (Note [Child lifecycle]). The child's end is
    closed here either way, the engine's too if ``start`` raises."""
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    hold_parent_end(ours.fileno())
    try:
        started = start(theirs.fileno())
    except BaseException:
        release_parent_end(ours.fileno())
        ours.close()
        raise
    finally:
        theirs.close()
    return started, Connection(ours.detach())


def _drop_parent_ends() -> None:
    if not _PARENT_ENDS:
        return
    null = os.open(os.devnull, os.O_RDWR)
    for fd in list(_PARENT_ENDS):
        with contextlib.suppress(OSError):  # the number stays valid: what closes it later closes /dev/null
            os.dup2(null, fd, inheritable=False)
    os.close(null)
    _PARENT_ENDS.clear()


os.register_at_fork(after_in_child=_drop_parent_ends)
