"""Handing frames to a worker's input ring by hand, as the engine's submit does, for tests that drive a worker one
batch at a time."""

from __future__ import annotations

import time
from collections.abc import Callable

from vpengine.transport.ring import SlotRing


def submitter(in_ring: SlotRing, cameras: list[str]) -> Callable[[str, float], int]:
    """``submit(camera, value)``: a frame of ``cameras``' camera whose ``x`` is ``value`` and ``y`` ``value + 0.5``
    everywhere, published with its frame id ``int(value)``; returns its seq (its origin)."""
    writer = in_ring.writer()

    def submit(camera: str, value: float) -> int:
        slot = writer.acquire(timeout=1.0)
        assert slot is not None
        slot.tensors["x"].fill_(value)
        slot.tensors["y"].fill_(value + 0.5)
        now = time.monotonic()
        return writer.publish(slot, int(value), now, now, tag=cameras.index(camera))

    return submit
