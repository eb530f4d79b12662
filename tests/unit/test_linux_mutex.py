"""transport/linux.py: the robust mutex keeps the GIL for what never blocks and releases it for what may."""

from __future__ import annotations

import mmap
import threading
import time

from helpers.builds import in_threads
from vpengine.transport.linux import MUTEX_BYTES, RobustMutex, address_of, mutex_init


def _mutex() -> tuple[mmap.mmap, RobustMutex]:
    buf = mmap.mmap(-1, MUTEX_BYTES)
    addr = address_of(buf, 0)
    mutex_init(addr)
    return buf, RobustMutex(addr)


def test_a_contended_lock_waits_with_the_gil_released():
    """The holder needs the GIL to unlock: a waiter that kept it would never get the lock (a deadlock, which stalls
    every thread of the process: this test then hangs until the run's time limit rather than failing)."""
    buf, m = _mutex()
    held, got = threading.Event(), threading.Event()

    def hold() -> None:
        with m:
            held.set()
            time.sleep(0.3)  # then Python code, which needs the GIL, unlocks

    def take() -> None:
        with m:
            got.set()

    holder = threading.Thread(target=hold, daemon=True)
    holder.start()
    assert held.wait(10)
    taker = threading.Thread(target=take, daemon=True)
    t = time.monotonic()
    taker.start()
    assert got.wait(10), "the waiter never got the lock: it waited holding the GIL"
    assert time.monotonic() - t >= 0.1  # it did wait for the holder
    holder.join(10)
    taker.join(10)
    buf.close()


def test_a_free_lock_is_taken_and_given_back_in_turn():
    buf, m = _mutex()
    inside, overlaps = [0], []

    def work() -> None:
        for _ in range(500):
            with m:
                inside[0] += 1
                time.sleep(0)  # gives the GIL away inside: another thread would get in without the mutex
                overlaps.append(inside[0])
                inside[0] -= 1

    in_threads(work, 4)
    assert len(overlaps) == 2000 and max(overlaps) == 1  # one at a time, none lost
    assert m.owner_died == 0
    buf.close()
