"""A stand-in camera for the live-capture code (Note [Live capture] in vpengine.io.sources)."""

from __future__ import annotations

import threading
import time

import cv2
import numpy as np


class FakeCamera:
    """A ``cv2.VideoCapture`` stand-in: ``read`` blocks until the test delivers the next frame (frame i is all i)."""

    def __init__(self, end_at: int | None = None, fail_at: int | None = None, width: int = 8, height: int = 6) -> None:
        self.width, self.height = width, height
        self.ready = threading.Semaphore(0)
        self.i = 0
        self.end_at, self.fail_at = end_at, fail_at

    def isOpened(self) -> bool:
        return True

    def get(self, prop: int) -> float:
        sizes = {cv2.CAP_PROP_FRAME_WIDTH: self.width, cv2.CAP_PROP_FRAME_HEIGHT: self.height}
        return float({**sizes, cv2.CAP_PROP_FPS: 30.0}.get(prop, 0.0))

    def deliver(self, n: int = 1) -> None:
        for _ in range(n):
            self.ready.release()

    def read(self) -> tuple[bool, np.ndarray | None]:
        self.ready.acquire()
        if self.i == self.fail_at:
            raise OSError("device unplugged")
        if self.i == self.end_at:
            return False, None
        self.i += 1
        return True, np.full((self.height, self.width, 3), (self.i - 1) % 256, np.uint8)

    def release(self) -> None:
        pass

    def stream(self, fps: float) -> threading.Thread:
        """Deliver frames at ``fps`` from a thread, as a camera does whether or not anyone reads, until the end."""

        def run() -> None:
            for _ in range((self.end_at or 0) + 1):
                self.deliver()
                time.sleep(1.0 / fps)

        t = threading.Thread(target=run, daemon=True)
        t.start()
        return t
