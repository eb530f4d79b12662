"""Frames into the engine without a copy: ``Engine.frame_slot`` lends an input slot (Note [Frame slots] in
core.py)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from vpengine.engine.boundary import Placement
from vpengine.transport.ring import SlotInfo

if TYPE_CHECKING:
    from vpengine.engine import Engine


class FrameSlot:
    """An input slot lent by ``Engine.frame_slot``: write the frame into ``array``, then leave the with-block."""

    def __init__(
        self,
        engine: Engine,
        frame_id: int | None,
        timestamp: float | None,
        size: tuple[int, int] | None,
        camera: int,
    ) -> None:
        self._engine = engine
        self._camera = camera
        # capture time in seconds; may be set inside the block (default: when it ends)
        self.timestamp = timestamp
        self._frame_id_arg = frame_id
        self._size = size
        self.frame_id: int | None = None  # set when the block ends and the frame is submitted
        self._array: np.ndarray | None = None
        self._slot: SlotInfo | None = None
        self._cancelled = False

    @property
    def array(self) -> np.ndarray | None:
        """The writable frame: ``(height, width, 3)`` of the input dtype (None outside the block)."""
        return self._array

    @array.setter
    def array(self, value: np.ndarray) -> None:
        """``ok, slot.array = cap.read(image=slot.array)``: what a writer hands back must be the lent array itself.
        A writer that allocated a new array instead (OpenCV does when the sizes differ) wrote nothing into the
        slot: refused, naming both sizes, rather than submitting whatever the slot held before."""
        arr = self._array
        if arr is None:
            raise RuntimeError("a FrameSlot's array exists only inside its with-block")
        if not isinstance(value, np.ndarray):
            raise ValueError(f"slot.array takes the slot's own array back, got a {type(value).__name__}")
        if value.shape != arr.shape or value.dtype != arr.dtype:
            size = (
                "; open the slot with frame_slot(size=(height, width)) of your frames"
                if value.ndim >= 2 and value.shape[:2] != arr.shape[:2]
                else ""
            )
            raise ValueError(
                f"the frame written is {value.shape} {value.dtype}, the slot {arr.shape} {arr.dtype}: a writer that "
                f"cannot write into the slot allocated a new array, and nothing reached the slot{size}"
            )
        if value.__array_interface__["data"][0] != arr.ctypes.data:
            raise ValueError(
                f"the frame was written into another {value.shape[1]}x{value.shape[0]} {value.dtype} array, not into "
                "the slot: write into slot.array itself (cap.read(image=slot.array), np.copyto(slot.array, frame))"
            )

    def cancel(self) -> None:
        """Submit nothing when the block ends (e.g. the camera returned no frame)."""
        self._cancelled = True

    def __enter__(self) -> FrameSlot:
        eng = self._engine
        if self._slot is not None or self.frame_id is not None or self._cancelled:
            raise RuntimeError("a FrameSlot is used for one with-block; call engine.frame_slot() again")
        fence = eng._res.fence
        fence.__enter__()  # the slot is mapped memory: held for the whole block (Note [Unmapping at stop])
        # the camera's filling lock for the whole block (Note [Frames of several cameras at once] in core.py)
        lock = eng._filling_locks[self._camera]
        lock.acquire()
        slot = None
        try:
            eng._require_running()
            slot = eng._acquire_input()
            # the slot itself when the frames are the models' size; else a buffer the frame is fitted from at the
            # end (Note [Frame grid] in boundary.py)
            array = eng._frame_views[slot.index] if self._size is None else eng._staging(self._camera, self._size)
        except BaseException:
            if slot is not None:
                eng._input_writer.abort(slot)
            lock.release()
            fence.leave()
            raise
        eng._filling.add(threading.get_ident())
        self._slot, self._array = slot, array
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        eng, slot, arr = self._engine, self._slot, self._array
        assert slot is not None and arr is not None
        self._array, self._slot = None, None  # the slot is the engine's again: no writes after the block
        try:
            if exc_type is not None or self._cancelled or eng._state != "running":
                eng._input_writer.abort(slot)
                return
            if self._size is None:  # written in place: the frame fills the canvas
                fill: Callable[[np.ndarray], Placement] = lambda _: eng.boundary.placement(arr.shape[:2])  # noqa: E731
            else:  # fitted into the slot from the buffer lent (Note [Frame grid] in boundary.py)
                fill = lambda view: eng.boundary.write(eng.boundary.check(arr), view)  # noqa: E731
            # the timestamp may have been set inside the block
            self.frame_id = eng._enter_frame(
                slot, fill, self._frame_id_arg, self.timestamp, time.monotonic(), self._camera
            )
        finally:
            eng._filling.discard(threading.get_ident())
            eng._filling_locks[self._camera].release()
            eng._res.fence.leave()
