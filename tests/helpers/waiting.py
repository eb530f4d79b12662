"""Waiting on engines and processes in integration tests."""

from __future__ import annotations

import queue
import time
from collections.abc import Callable, Iterable
from typing import Any

import psutil


def wait_for(
    cond: Callable[[], Any], timeout: float = 20.0, what: str = "condition", show: Callable[[], Any] | None = None
) -> None:
    """Poll ``cond`` until it is true; AssertionError naming ``what`` (and ``show()``) after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}" + (f": {show()}" if show else ""))


def alive(pids: Iterable[int]) -> list[int]:
    """Those of ``pids`` that run (zombies are gone)."""
    out = []
    for p in pids:
        try:
            if psutil.Process(p).status() != psutil.STATUS_ZOMBIE:
                out.append(p)
        except psutil.NoSuchProcess:
            pass
    return out


class Commands:
    """Commands for a control loop (vpengine.ros2.control.ControlLoop): :meth:`put` (kind, key, value) triples;
    :meth:`wait` is its ``wait_commands``, one command per call."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[tuple[str, str, str]] = queue.SimpleQueue()

    def put(self, command: tuple[str, str, str]) -> None:
        self._queue.put(command)

    def wait(self, timeout: float) -> list[tuple[str, str, str]]:
        try:
            return [self._queue.get(timeout=timeout)]
        except queue.Empty:
            return []
