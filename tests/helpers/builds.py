"""Another thread's build holding a build lock (Note [One build at a time] in models/build.py); whether this Python's
collector can hold full collections off (Note [Building beside serving threads] in runtime/threads.py); a function
run in several threads at once."""

from __future__ import annotations

import contextlib
import gc
import threading
from collections.abc import Callable, Iterator

from vpengine.models.build import BuildLock
from vpengine.runtime.threads import _NO_FULL_COLLECTION


def full_collections_can_be_held_off() -> bool:
    """Whether this Python's collector takes a third threshold (an incremental one, 3.14.0-3.14.4, ignores it)."""
    before = gc.get_threshold()
    gc.set_threshold(before[0], before[1], _NO_FULL_COLLECTION)
    try:
        return gc.get_threshold()[2] == _NO_FULL_COLLECTION
    finally:
        gc.set_threshold(*before)


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


def in_threads(target: Callable[[], None], n: int, timeout: float = 30) -> None:
    """Run ``target`` in ``n`` threads at once and wait for them all (``timeout`` each)."""
    threads = [threading.Thread(target=target) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout)
    assert not any(t.is_alive() for t in threads), f"{target.__name__} did not end in {timeout} s"
