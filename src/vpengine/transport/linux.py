"""Linux primitives for cross-process mailboxes: a robust process-shared mutex and futex wait/wake.

Python has no atomics, so every metadata update in a mailbox happens under a mutex that lives in the shared
metadata itself. It is a glibc ``pthread_mutex_t`` with two attributes that matter:

* ``PTHREAD_PROCESS_SHARED``: it works across processes mapping the same memory;
* ``PTHREAD_MUTEX_ROBUST``: if its owner dies while holding it (SIGKILL inside a critical section), the next
  locker gets ``EOWNERDEAD`` instead of hanging forever. We mark it consistent and go on; the critical sections
  are written so that any prefix of their stores leaves the mailbox usable (see ``ring.py``).

Lock and unlock are full barriers, which is what makes the plain stores Python does inside the critical section
visible in order on ARM (Jetson) as well as on x86.

Wake-ups use raw futexes on a 32-bit word in the same shared memory: a waiter reads the word under the mutex,
unlocks, and sleeps in ``FUTEX_WAIT`` only if the word still has that value, so no wake-up is lost; a waker bumps
the word and calls ``FUTEX_WAKE``. Unlike process-shared condition variables (whose glibc implementation can block
a signaller forever when a waiter process is killed mid-wait), a futex keeps no waiter state in user memory, so a
dead waiter costs nothing. Every wait has a timeout: nothing in vpengine sleeps unboundedly or spins.

ctypes releases the GIL around foreign calls, so a thread sleeping here does not stall the other threads. Calls that
never block (a free mutex taken with ``trylock``, an unlock, a wake) keep it instead: releasing it around a few
hundred nanoseconds of work costs the caller a turn in the GIL's queue each time it wants it back, behind every other
thread of the process (thread mode: the workers, the caller's threads), several times per mailbox operation.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import platform
import sys

if not sys.platform.startswith("linux"):  # pragma: no cover - import-time guard
    raise ImportError("vpengine's transport needs Linux (memfd, futex, robust process-shared mutexes)")

_LIBC = ctypes.util.find_library("c") or "libc.so.6"
_libc = ctypes.CDLL(_LIBC, use_errno=True)  # releases the GIL around each call: for calls that may block
_held = ctypes.PyDLL(_LIBC, use_errno=True)  # keeps it: for calls that never block

_SYS_FUTEX = {"x86_64": 202, "aarch64": 98}.get(platform.machine())
if _SYS_FUTEX is None:  # pragma: no cover
    raise ImportError(f"unsupported CPU architecture {platform.machine()!r}; expected x86_64 or aarch64")

_FUTEX_WAIT = 0
_FUTEX_WAKE = 1
_PTHREAD_PROCESS_SHARED = 1
_PTHREAD_MUTEX_ROBUST = 1

#: Bytes reserved for one mutex. glibc's pthread_mutex_t is 40 bytes on x86_64 and 48 on aarch64.
MUTEX_BYTES = 64

_libc.syscall.restype = ctypes.c_long
_libc.pthread_mutex_lock.argtypes = [ctypes.c_void_p]
_libc.pthread_mutex_consistent.argtypes = [ctypes.c_void_p]
_libc.pthread_mutex_init.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
_held.syscall.restype = ctypes.c_long
_held.pthread_mutex_trylock.argtypes = [ctypes.c_void_p]
_held.pthread_mutex_unlock.argtypes = [ctypes.c_void_p]


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


def address_of(buffer: object, offset: int) -> int:
    """Address of byte ``offset`` of a writable buffer (an mmap). Keeps no reference: the caller keeps the buffer."""
    return ctypes.addressof(ctypes.c_char.from_buffer(buffer, offset))  # type: ignore[arg-type]


def mutex_init(addr: int) -> None:
    """Initialise a robust, process-shared mutex at ``addr`` (MUTEX_BYTES of zeroed shared memory)."""
    attr = ctypes.create_string_buffer(64)
    for call, args in (
        (_libc.pthread_mutexattr_init, (attr,)),
        (_libc.pthread_mutexattr_setpshared, (attr, _PTHREAD_PROCESS_SHARED)),
        (_libc.pthread_mutexattr_setrobust, (attr, _PTHREAD_MUTEX_ROBUST)),
        (_libc.pthread_mutex_init, (ctypes.c_void_p(addr), attr)),
    ):
        rc = call(*args)
        if rc != 0:
            raise OSError(rc, f"{call.__name__} failed: {os.strerror(rc)}")
    _libc.pthread_mutexattr_destroy(attr)


class RobustMutex:
    """Context manager over a robust process-shared mutex at a fixed address.

    ``owner_died`` counts how often a previous owner died holding it; callers that keep invariants across the
    critical section can look at it, and the supervisor repairs a dead worker's state anyway.
    """

    __slots__ = ("_addr", "owner_died")

    def __init__(self, addr: int) -> None:
        self._addr = ctypes.c_void_p(addr)
        self.owner_died = 0

    def __enter__(self) -> RobustMutex:
        rc = _held.pthread_mutex_trylock(self._addr)
        if rc == errno.EBUSY:  # held by another thread or process: wait for it with the GIL released
            rc = _libc.pthread_mutex_lock(self._addr)
        if rc == errno.EOWNERDEAD:
            self.owner_died += 1
            _libc.pthread_mutex_consistent(self._addr)
        elif rc != 0:
            raise OSError(rc, f"locking the mutex failed: {os.strerror(rc)}")
        return self

    def __exit__(self, *exc: object) -> None:
        rc = _held.pthread_mutex_unlock(self._addr)
        if rc != 0:
            raise OSError(rc, f"pthread_mutex_unlock failed: {os.strerror(rc)}")


def futex_wait(addr: int, expected: int, timeout: float) -> None:
    """Sleep while the u32 at ``addr`` equals ``expected``, at most ``timeout`` seconds.

    Returns on a wake, a timeout, a changed value or a signal; callers re-check their condition in a loop.
    """
    timeout = max(0.0, timeout)
    ts = _Timespec(int(timeout), int((timeout - int(timeout)) * 1e9))
    rc = _libc.syscall(
        _SYS_FUTEX, ctypes.c_void_p(addr), _FUTEX_WAIT, ctypes.c_uint32(expected), ctypes.byref(ts), None, 0
    )
    if rc != 0:
        err = ctypes.get_errno()
        if err not in (errno.EAGAIN, errno.ETIMEDOUT, errno.EINTR):
            raise OSError(err, f"futex wait failed: {os.strerror(err)}")


def futex_wake(addr: int) -> None:
    """Wake every waiter sleeping on the u32 at ``addr``."""
    rc = _held.syscall(_SYS_FUTEX, ctypes.c_void_p(addr), _FUTEX_WAKE, 0x7FFFFFFF, None, None, 0)
    if rc < 0:
        err = ctypes.get_errno()
        raise OSError(err, f"futex wake failed: {os.strerror(err)}")


def memfd(name: str, nbytes: int) -> int:
    """An anonymous shared-memory file of ``nbytes`` (owner-only, no name in /dev/shm, freed with its last user).

    memfd_create gives a file that no other process can open by name: it is reachable only through a file
    descriptor that we hand over explicitly (SCM_RIGHTS). Nothing is left in /dev/shm, even after SIGKILL.
    """
    fd = os.memfd_create(f"vpengine-{name}"[:249], os.MFD_CLOEXEC)
    try:
        os.ftruncate(fd, nbytes)
    except BaseException:
        os.close(fd)
        raise
    return fd
