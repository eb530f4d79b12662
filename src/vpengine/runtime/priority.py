"""Priorities: which lanes give way when the device cannot serve them all (Note [Give way] in governor.py).

A lane is one (model, camera) pair with its own control-block entry (Note [Cameras] in worker.py). Its priority is a
key ``(head priority, camera priority)``, compared head first; higher is more important. Both come from the config
(``heads[].priority``, ``cameras[].priority``) and live in the control block from start, where ``Engine.set_priority``
changes them, so the governor and every worker, in any process, read the current ones. The foundation model serves
every head: its lane of a camera ranks with the most important head lane of that camera, and is throttled only as
far as that lane allows (``Governor``).

The device learns of them too. A model's CUDA stream runs at a higher stream priority the more important the model
(``stream_levels``): that counts where models share a context (thread mode, process groups, MPS clients). The
governor writes each model's level into the control block at start and whenever priorities or heads change, a worker
starts on a stream of that level and moves to another before a run when it changed (Note [Stream priority at run
time] in device.py), so ``set_priority`` reaches the GPU within a fraction of a second. In process mode a head less
important than the engine's most important one is an MPS client of below-normal priority, unless its
``mps_priority`` says otherwise; that follows the config, not later ``set_priority`` calls (a client's priority
cannot change under a running context).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from vpengine.config import EngineConfig
from vpengine.runtime.control import ControlBlock


def _model_priority(cfg: EngineConfig, model: str) -> int:
    """A model's configured priority; the foundation model's is its most important head's."""
    if model != "foundation":
        return cfg.head(model).priority
    return max((h.priority for h in cfg.heads), default=0)


#: Stream levels above the default that torch's stream pools have (priorities 0 to -3): more distinct priorities
#: than levels share the lowest.
TOP_LEVEL = 3


def stream_levels(priorities: Mapping[str, int], top: int = TOP_LEVEL) -> dict[str, int]:
    """Each model's stream level from its priority (``priorities``: model -> priority, the foundation model's its
    most important head's): the number of distinct priorities below its own, so equal priorities (the default)
    leave every stream at the default; with more distinct priorities than ``top`` + 1 the most important keep their
    own levels down from ``top`` and the least important share the default."""
    values = set(priorities.values())
    return {m: max(0, min(sum(v < p for v in values), top - sum(v > p for v in values))) for m, p in priorities.items()}


def mps_below_normal(cfg: EngineConfig, model: str) -> bool:
    """The MPS client priority of ``model``'s process: its ``mps_priority``, else below normal for a head less
    important than the engine's most important head (MPS has only the two levels)."""
    chosen = cfg.model(model).mps_priority
    if chosen is not None:
        return chosen == "below_normal"
    return _model_priority(cfg, model) < _model_priority(cfg, "foundation")


def priority_key(control: ControlBlock, entry: str) -> tuple[int, int]:
    """A lane's priority key as the control block holds it now: its head's priority, then its camera's."""
    return int(control.get(entry, "priority")), int(control.get(entry, "camera_priority"))


def least_important(control: ControlBlock, entries: Sequence[str]) -> int:
    """The index of the least important of ``entries`` (lanes' control-block entries, in the configured order of
    their cameras) by ``priority_key``; among equals the last: the camera last in the configured order."""
    return min(range(len(entries)), key=lambda i: (*priority_key(control, entries[i]), -i))
