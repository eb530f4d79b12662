"""The one store of recent input frames by frame id, for whoever draws a result on its own frame (Note [Pictures
and frames] in ``vpengine.web.pictures``): the pipeline's sinks and live view, the ROS 2 core's overlays and
headers."""

from __future__ import annotations

import collections
import threading
from typing import Generic, TypeVar

import numpy as np

T = TypeVar("T")


class RecentFrames(Generic[T]):
    """Engine frame id -> the input frame and a tag of the caller's (its output name, its ROS header). Bounded,
    thread-safe: the ``frames`` newest frames and the ``tags`` newest tags are kept (``tags`` defaults to
    ``frames``; ``frames`` 0 keeps tags alone). A frame id that was forgotten, or never added, gives None.

    Whoever feeds the engine adds a frame *before* a result for it can be looked up: a fast head's output can come
    back before ``submit`` returns (add it first, with an id chosen up front, or hold one lock around ``submit``
    and ``add`` that the lookup takes too)."""

    def __init__(self, frames: int, tags: int | None = None) -> None:
        tags = max(frames, 1) if tags is None else tags
        if tags < 1 or frames < 0:
            raise ValueError(f"RecentFrames needs frames >= 0 and tags >= 1, got {frames} and {tags}")
        self._tags: collections.OrderedDict[int, T] = collections.OrderedDict()
        self._frames: collections.OrderedDict[int, np.ndarray] = collections.OrderedDict()
        self._n_tags, self._n_frames = tags, frames
        self._lock = threading.Lock()

    @property
    def keeps_frames(self) -> bool:
        return self._n_frames > 0

    def add(self, frame_id: int, tag: T, frame: np.ndarray | None = None) -> None:
        with self._lock:
            self._tags[frame_id] = tag
            if len(self._tags) > self._n_tags:
                self._tags.popitem(last=False)
            if self._n_frames and frame is not None:
                self._frames[frame_id] = frame
                if len(self._frames) > self._n_frames:
                    self._frames.popitem(last=False)

    def tag(self, frame_id: int) -> T | None:
        with self._lock:
            return self._tags.get(frame_id)

    def frame(self, frame_id: int) -> np.ndarray | None:
        """The input frame of ``frame_id``: a :data:`vpengine.web.FrameLookup`."""
        with self._lock:
            return self._frames.get(frame_id)
