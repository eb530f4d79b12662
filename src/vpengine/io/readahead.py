"""Frames read on a thread of their own, a few ahead of whoever takes them (Note [Read ahead])."""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from typing import Generic, TypeVar

T = TypeVar("T")

_ITEM, _END, _ERROR = "item", "end", "error"
_NONE_LEFT = object()


class ReadAhead(Iterator[T], Generic[T]):
    """Note [Read ahead]: decoding a frame of a video (or an image, or a bag's message) took as long on the
    lockstep loop's thread as the rest of its host work, and the engine's models waited for both. Here a thread
    reads the source while the loop writes the frame before into the engine and waits for its outputs; the loop
    takes the frames from a queue of at most ``ahead``, in the source's order, nothing skipped. Whatever the source
    raises is raised by ``next`` at the place it happened, after every frame before it, as the same exception;
    the end of the source ends the iteration there. ``limit`` frames at most are read (a run's ``max_frames``), so
    the source reads nothing and reports nothing (a skipped image, a bad message) that the run never takes.

    For sources read whole, not live ones: a camera already has its own thread that keeps only the newest frame
    (Note [Live capture] in vpengine.io.sources), which frames queued here would make stale. ``close`` stops the
    reader at its next frame and closes the source's iterator on the reader's thread (a generator is closed by the
    thread that runs it); later ``next`` calls end the iteration."""

    def __init__(self, frames: Iterable[T], ahead: int, limit: int | None = None, name: str = "vpengine-read") -> None:
        if ahead < 1:
            raise ValueError(f"ahead must be >= 1 frame, got {ahead}")
        self._q: queue.Queue[tuple[str, object]] = queue.Queue(ahead)
        self._stop = threading.Event()
        self._ended = False
        self._thread = threading.Thread(target=self._read, args=(iter(frames), limit), name=name, daemon=True)
        self._thread.start()

    def __next__(self) -> T:
        if self._ended:
            raise StopIteration
        kind, value = self._q.get()
        if kind == _ITEM:
            return value  # type: ignore[return-value]
        self._ended = True
        if kind == _ERROR:
            assert isinstance(value, BaseException)
            raise value
        raise StopIteration

    def close(self, timeout: float = 2.0) -> None:
        """Stop reading; waits up to ``timeout`` s for a read in progress to end."""
        self._ended = True
        self._stop.set()
        while True:  # what was read ahead is not needed any more (and the reader may be waiting for room)
            try:
                self._q.get_nowait()
            except queue.Empty:
                break
        self._thread.join(timeout)

    def _read(self, frames: Iterator[T], limit: int | None) -> None:
        try:
            try:
                n = 0
                while limit is None or n < limit:
                    item = next(frames, _NONE_LEFT)
                    if item is _NONE_LEFT:
                        break
                    if not self._put(_ITEM, item):
                        return
                    n += 1
            finally:
                close = getattr(frames, "close", None)
                if close is not None:
                    close()
        except BaseException as e:  # raised in the taker's thread, where it would have been without us
            self._put(_ERROR, e)
            return
        self._put(_END, None)

    def _put(self, kind: str, value: object) -> bool:
        """Queue one entry, waiting for room; False once closed."""
        while not self._stop.is_set():
            try:
                self._q.put((kind, value), timeout=0.1)
                return True
            except queue.Full:
                continue
        return False
