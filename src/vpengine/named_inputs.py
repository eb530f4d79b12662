"""Inputs named after cameras: ``--source NAME=SPEC``, ``--input-topic NAME=TOPIC``, and the config of an engine
fed by them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from vpengine.config import NAME_RE, EngineConfig, load_config


def split_camera(text: str) -> tuple[str | None, str]:
    """``NAME=VALUE`` -> (NAME, VALUE) when NAME is a camera name (letters, digits, '_' and '-', starting with a
    letter); any other text -> (None, text): the one-camera spelling of a source or topic (``camera:0``,
    ``/camera/image_raw``, a path)."""
    name, sep, value = text.partition("=")
    if sep and NAME_RE.match(name.strip()):
        return name.strip(), value.strip()
    return None, text


def config_for_cameras(
    source: str | Path | dict[str, Any] | EngineConfig | None,
    names: list[str] | None,
    overrides: list[str] | None = None,
    what: str = "sources",
) -> EngineConfig:
    """The config of an engine fed by inputs named ``names`` (``--source NAME=SPEC``, ``--input-topic NAME=TOPIC``),
    or by one unnamed input (None). A config without ``cameras`` gets one per name, in the order given (their
    priority order); a config with cameras must name the same ones. ``overrides`` apply after the cameras are set,
    so they may name them (``heads.seg.cameras=[rear]``). ValueError naming both lists when they differ."""
    overrides = list(overrides or [])
    if names:
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"the {what} must have different names; repeated: {dup}")
        base = load_config(source)  # without the overrides, which may name the cameras themselves
        if not base.cameras and not any(o.partition("=")[0].strip() == "cameras" for o in overrides):
            overrides.insert(0, "cameras=" + json.dumps([{"name": n} for n in names]))
    cfg = load_config(source, overrides)
    configured = cfg.camera_names()
    if names and sorted(names) != sorted(configured):
        raise ValueError(
            f"the {what} are named {list(names)} but the config's cameras are {configured}: name one of the {what} "
            f"after each camera (or leave cameras out of the config)"
        )
    if not names and len(configured) > 1:
        raise ValueError(
            f"the config has cameras {configured}: give one of the {what} for each, named NAME=... after its camera"
        )
    return cfg
