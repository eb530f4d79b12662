"""vpengine: one vision foundation model per frame, its features shared on the device with many task heads."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from vpengine._version import __version__ as __version__

if TYPE_CHECKING:
    from vpengine.config import ConfigError, EngineConfig, load_config
    from vpengine.engine import Engine, EngineDeadError, EngineStartError, FrameSlot, Result

__all__ = [
    "ConfigError",
    "Engine",
    "EngineConfig",
    "EngineDeadError",
    "EngineStartError",
    "FrameSlot",
    "Result",
    "load_config",
]


def __getattr__(name: str) -> Any:  # lazy: `import vpengine` stays light for worker start-up and the CLI
    if name in ("Engine", "EngineDeadError", "EngineStartError", "FrameSlot", "Result"):
        from vpengine.engine import core as engine

        return getattr(engine, name)
    if name in ("ConfigError", "EngineConfig", "load_config"):
        from vpengine import config

        return getattr(config, name)
    raise AttributeError(f"module 'vpengine' has no attribute {name!r}")
