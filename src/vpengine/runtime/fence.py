"""The fence between ``Engine.stop()`` and everything that still reads or writes the engine's mailboxes.

Note [Unmapping at stop]
~~~~~~~~~~~~~~~~~~~~~~~~
A mailbox's metadata (its mutex, its futex words) is a shared mapping; a thread that locks the mutex after the
mapping is gone does not get an exception, it segfaults the process. Two kinds of users can still be inside the
mailboxes when ``stop()`` runs: API calls of other threads (``latest``/``results``/``wait``/``submit``, an open
``frame_slot`` block), and, in thread mode, a worker thread that ``stop()`` gave up on (its model did not return
within ``runtime.stop_timeout_s``; a Python thread cannot be killed). So every API call runs inside the fence
(``with fence:``), a thread that may still touch the mappings is held (``hold_until_gone``), and ``close(unmap)``
lets no new call in (they raise ``EngineDeadError``) and unmaps when the last user has left: at once if none is
inside, else in the thread of whoever leaves last. ``stop()`` itself never waits for them; a thread that never
returns keeps the mappings (its process's memory, no /dev/shm entry) until the process ends. A mailbox retired while
the engine runs (a head removed) is unmapped the same way, by ``defer``: once no call that may hold it is inside.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from vpengine.runtime.supervisor import EngineDeadError


class MappingFence:
    """Counts the users of an engine's mappings; see Note [Unmapping at stop]. A use is counted in the *epoch* it
    began in, so that ``defer`` waits only for the uses that began before it, not for every later one."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._users = 0
        self._closing = False
        self._unmap: Callable[[], None] | None = None
        self._epoch = 0
        self._active: dict[int, int] = {}  # epoch -> uses begun in it and not ended
        self._deferred: list[tuple[int, Callable[[], None]]] = []  # (the epoch it waits out, what to run)
        self._local = threading.local()  # each thread's epochs of its uses, innermost last

    @property
    def closing(self) -> bool:
        return self._closing

    def _begin(self) -> None:  # the caller holds the lock
        self._users += 1
        self._active[self._epoch] = self._active.get(self._epoch, 0) + 1
        self._epochs().append(self._epoch)

    def _end(self) -> list[Callable[[], None]]:  # the caller holds the lock; returns the deferred now due
        self._users -= 1
        epoch = self._epochs().pop()
        left = self._active[epoch] - 1
        if left:
            self._active[epoch] = left
        else:
            del self._active[epoch]
        return self._take_deferred() if self._deferred else []

    def _epochs(self) -> list[int]:
        epochs: list[int] | None = getattr(self._local, "epochs", None)
        if epochs is None:
            epochs = self._local.epochs = []
        return epochs

    def enter(self) -> bool:
        """Start a use; False (and no use started) once closing."""
        with self._lock:
            if self._closing:
                return False
            self._begin()
            return True

    def leave(self) -> None:
        """End a use (in the thread that began it); the last one out after ``close`` unmaps."""
        self.__exit__()

    def __enter__(self) -> MappingFence:  # enter(), raising; inlined: every API call goes through here
        with self._lock:
            if self._closing:
                raise EngineDeadError("engine is stopped")
            self._begin()
        return self

    def __exit__(self, *exc: object) -> None:
        with self._lock:
            due = self._end()
            unmap = self._take_unmap()
        for fn in due:
            fn()
        if unmap is not None:
            unmap()

    def defer(self, unmap: Callable[[], None]) -> None:
        """Run ``unmap`` once every use begun before now has ended (now, if none is inside): a mailbox retired while
        the engine runs. Uses begun later cannot reach it, and are not waited for."""
        with self._lock:
            self._deferred.append((self._epoch, unmap))
            self._epoch += 1
            due = self._take_deferred()
        for fn in due:
            fn()

    def _take_deferred(self) -> list[Callable[[], None]]:
        oldest = min(self._active, default=self._epoch)
        due = [fn for mark, fn in self._deferred if mark < oldest]
        self._deferred = [(mark, fn) for mark, fn in self._deferred if mark >= oldest]
        return due

    def hold_until_gone(self, thread: threading.Thread) -> None:
        """Count ``thread`` as a user until it ends (it may still touch the mappings), even past ``close``."""
        with self._lock:
            self._users += 1
        try:
            threading.Thread(target=self._leave_after, args=(thread,), name="vpengine-unmap-after", daemon=True).start()
        except RuntimeError:  # the interpreter is exiting: the process's end unmaps everything
            pass

    def _leave_after(self, thread: threading.Thread) -> None:
        thread.join()
        with self._lock:
            self._users -= 1
            unmap = self._take_unmap()
        if unmap is not None:
            unmap()

    def close(self, unmap: Callable[[], None]) -> None:
        """Admit no new use; run ``unmap`` once no use is left (now, or when the last one ends)."""
        with self._lock:
            self._closing = True
            pending, self._deferred = [fn for _, fn in self._deferred], []  # the whole engine goes: its parts too
            self._unmap = _then(pending, unmap) if pending else unmap
            unmap_now = self._take_unmap()
        if unmap_now is not None:
            unmap_now()

    def _take_unmap(self) -> Callable[[], None] | None:
        """The unmap to run now, if it is due (caller holds the lock); it runs exactly once."""
        if not self._closing or self._users > 0 or self._unmap is None:
            return None
        unmap, self._unmap = self._unmap, None
        return unmap


def _then(first: list[Callable[[], None]], last: Callable[[], None]) -> Callable[[], None]:
    def run() -> None:
        for fn in first:
            fn()
        last()

    return run
