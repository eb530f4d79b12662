"""What every frame source yields (:class:`Frame`) and the interface it has (:class:`Source`); the sources
themselves are in :mod:`vpengine.io.sources` and :mod:`vpengine.io.bag`."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np


@dataclass
class Frame:
    image: np.ndarray
    timestamp: float | None = None
    #: Where it came from (file name, frame index) for output naming.
    name: str = ""


class Source:
    """Iterable of frames. ``height``/``width``: the (first) frame's size; ``fps`` is None when the source has no
    natural rate."""

    color = "bgr"
    height: int
    width: int
    fps: float | None = None

    def __iter__(self) -> Iterator[Frame]:  # pragma: no cover - abstract
        raise NotImplementedError

    def __len__(self) -> int:
        """Number of frames, or 0 when unknown (live sources)."""
        return 0

    def close(self) -> None:
        pass

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
