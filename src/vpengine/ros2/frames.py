"""The book of recent input frames: engine frame id -> the input's exact header, and (optionally) its picture.

Its interface is four members (``add``, ``header``, ``frame``, ``keeps_frames``), so that one store of recent frames
shared by every door can take its place.
"""

from __future__ import annotations

import collections
import threading

import numpy as np

from vpengine.ros2.messages import Header


class FrameBook:
    """Engine frame id -> the input's exact :class:`Header` (and the input frame, for overlays). Bounded, thread-safe.

    See Note [Output headers] in :mod:`vpengine.ros2.core`. ``headers``: how many recent frames' headers are kept.
    ``frames`` > 0 keeps that many recent input frames (segmentation overlays and the web view draw on the picture
    the outputs were computed from); 0 keeps none.
    """

    def __init__(self, headers: int = 4096, frames: int = 0) -> None:
        if headers < 1 or frames < 0:
            raise ValueError(f"FrameBook needs headers >= 1 and frames >= 0, got {headers} and {frames}")
        self._headers: collections.OrderedDict[int, Header] = collections.OrderedDict()
        self._frames: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self._n_headers, self._n_frames = headers, frames
        self._lock = threading.Lock()

    @property
    def keeps_frames(self) -> bool:
        return self._n_frames > 0

    def add(self, frame_id: int, header: Header, frame: np.ndarray | None = None) -> None:
        """Book a frame before it is submitted; ``frame`` (BGR) is kept only when :attr:`keeps_frames`."""
        with self._lock:
            self._headers[frame_id] = header
            if len(self._headers) > self._n_headers:
                self._headers.popitem(last=False)
            if self._n_frames and frame is not None:
                self._frames[frame_id] = frame
                if len(self._frames) > self._n_frames:
                    self._frames.popitem(last=False)

    def header(self, frame_id: int) -> Header | None:
        """The input header of ``frame_id``; None when it is no longer (or never was) in the book."""
        with self._lock:
            return self._headers.get(frame_id)

    def frame(self, frame_id: int) -> np.ndarray | None:
        """The input picture of ``frame_id`` (BGR); None when not kept."""
        with self._lock:
            return self._frames.get(frame_id)
