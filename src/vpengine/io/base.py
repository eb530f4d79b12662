"""What every frame source yields (:class:`Frame`) and the interface it has (:class:`Source`); the sources
themselves are in :mod:`vpengine.io.sources` and :mod:`vpengine.io.bag`."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from vpengine.redact import redact

if TYPE_CHECKING:
    from vpengine.engine.results import Result
    from vpengine.ros2.messages import Header


@dataclass
class Frame:
    image: np.ndarray
    timestamp: float | None = None
    #: Where it came from (file name, frame index) for output naming.
    name: str = ""


class Source:
    """Iterable of frames. ``height``/``width``: the (first) frame's size; ``fps`` is None when the source has no
    natural rate. The rest is what a pipeline (``vpengine.pipeline``) reads from every source, with the defaults of
    a file that was read whole."""

    color = "bgr"
    height: int
    width: int
    fps: float | None = None
    #: Where the frames come from (a file, folder, bag, device or URL), as the summary names the source; None: made
    #: up (the synthetic scene), named by its kind.
    path: str | Path | int | None = None
    #: Frames come at the source's own rate (a camera, a live stream): read on a thread, the newest wins, and the
    #: pipeline does not pace them (Note [Live capture] in ``vpengine.io.sources``).
    live: bool = False
    #: Frames a newer frame replaced before the pipeline took them (a live source's, Note [Live capture]).
    missed: int = 0
    #: Inputs skipped as unreadable, each a dict naming it and why.
    skipped: Sequence[dict[str, Any]] = ()
    #: Inputs decoded only in part (truncated images, videos that end short: Note [Short videos]), by name.
    partial: Sequence[str] = ()
    #: The exact input header of the frame a result came from, given the result and its frame's name (a bag's,
    #: Note [Output headers] in ``vpengine.ros2.core``); None: the source has no headers.
    header_for: Callable[[Result, str], Header] | None = None

    @property
    def pace(self) -> Literal["lockstep", "realtime"]:
        """How a pipeline paces it by default: ``realtime`` for a source that plays at its own rate like a camera,
        ``lockstep`` (nothing skipped) for files."""
        return "realtime" if self.live else "lockstep"

    def describe(self) -> str:
        """How a summary names it: its path or URL without a password (Note [Redacting] in vpengine/redact.py),
        else its kind."""
        return type(self).__name__ if self.path is None else redact(str(self.path))

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
