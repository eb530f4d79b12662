"""Another thread's build holding a build lock (Note [One build at a time] in models/build.py)."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

from vpengine.models.build import BuildLock


@contextlib.contextmanager
def held_elsewhere(lock: BuildLock, what: str, thread: str = "builder") -> Iterator[None]:
    """``lock`` held by a thread named ``thread`` building ``what`` until the block ends; then it lets go."""
    entered, release = threading.Event(), threading.Event()

    def hold() -> None:
        with lock.held(what, 5):
            entered.set()
            release.wait(30)

    t = threading.Thread(target=hold, name=thread, daemon=True)
    t.start()
    try:
        assert entered.wait(10), f"{thread} never took the lock"
        yield
    finally:
        release.set()
        t.join(10)
