"""The engine side: the public ``Engine`` (``core``), how frames come in (``intake``, ``boundary``: the one door in
and out of the caller's pixel grid), what comes back (``results``) and its statistics (``stats``). See "Where a
change belongs" in docs/design.md."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from vpengine.engine.core import Engine, EngineDeadError, EngineStartError, FrameSlot, Result

__all__ = ["Engine", "EngineDeadError", "EngineStartError", "FrameSlot", "Result"]


def __getattr__(name: str) -> Any:  # lazy: a worker importing the boundary or results does not import the engine
    if name in __all__:
        from vpengine.engine import core

        return getattr(core, name)
    raise AttributeError(f"module 'vpengine.engine' has no attribute {name!r}")
