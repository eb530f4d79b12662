"""Heads added and removed while the engine runs (``Engine.add_head``, ``Engine.remove_head``; Note [Heads at run
time] in runtime/lanes.py).

An added head is validated like the config file (the whole config with it, so errors name ``heads.N.field``), planned
against the running foundation model, given a free seat and its own output mailbox, and its worker is started and
warmed up while the backbone and the other heads keep serving; only once it is ready do the results, the boundary and
the governor learn of it, and the engine's config and plan include it. A failure at any step leaves the engine as it
was. A removed head's worker is stopped, its unanswered frames answered, its seat given back (or, for a head of the
config, its entries retired), and its output mailbox unmapped once no call in flight can hold it.
"""

from __future__ import annotations

import gc
import logging
import threading
from collections.abc import Mapping
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import yaml

from vpengine.config import EngineConfig, HeadConfig, load_config
from vpengine.models.weights import check_checkpoints
from vpengine.runtime.lanes import Lanes, make_lanes
from vpengine.runtime.plan import Plan, check_preallocation, mailboxes, make_plan
from vpengine.runtime.worker import WorkerSpec
from vpengine.transport.ring import SlotRing

if TYPE_CHECKING:
    from vpengine.engine.core import Engine

log = logging.getLogger("vpengine")

#: one add or remove at a time, per process (they rename shared entries, which must not interleave)
_LOCK = threading.Lock()


def head_spec(plan: Plan, rings: dict[str, SlotRing], name: str, config: dict[str, Any]) -> WorkerSpec:
    """The worker of head ``name`` (of ``plan``), its engine's config being ``config``."""
    return WorkerSpec(
        name=name,
        role="head",
        config=config,
        upstream=plan.features,
        upstream_meta=plan.feature_meta,
        lanes=plan.lanes.of(name),
        in_ring=rings["features"].desc,
        out_ring=rings[f"out.{name}"].desc,
        notify_output=True,
    )


def _head_data(head: HeadConfig | dict[str, Any] | str) -> dict[str, Any]:
    if isinstance(head, HeadConfig):
        return head.model_dump(mode="json", exclude_unset=True)
    if isinstance(head, str):
        data = yaml.safe_load(head)
        if not isinstance(data, dict):
            raise ValueError(f"a head's config is a mapping (name: ..., model: ...); got {head!r}")
        return data
    if isinstance(head, dict):
        return dict(head)
    raise TypeError(f"add_head takes a head's config (dict, YAML text or HeadConfig); got {type(head).__name__}")


def _rename(engine: Engine, renames: dict[str, str], clear: bool) -> None:
    """Rename control-block entries and features readers (``clear``: zeroed first, a seat given back)."""
    control, features = engine._res.control, engine._res.rings["features"]
    assert control is not None
    readers = {r.name for r in features.desc.readers}
    for old, new in renames.items():
        if clear:
            control.clear(old)
        control.rename(old, new)
        if old in readers:
            if clear:
                features.clear_reader(old)
            features.rename_reader(old, new)


def add_head(engine: Engine, head: HeadConfig | dict[str, Any] | str) -> str:
    engine._require_running()
    res = engine._res
    with _LOCK:
        raw = engine.config.model_dump(mode="json")
        cfg = load_config({**raw, "heads": [*raw["heads"], _head_data(head)]})
        h = cfg.heads[-1]
        if h.input_mode == "fifo":
            raise ValueError(f"head {h.name!r}: input_mode fifo is for heads configured at start; add it as latest")
        seats = engine.lanes.seats
        if not seats:
            raise RuntimeError(
                f"no room for head {h.name!r}: runtime.spare_heads is {engine.config.runtime.spare_heads} and every "
                "seat is taken by a head added earlier; remove one, or start the engine with more spare heads"
            )
        lanes = make_lanes(cfg, seats[1:])
        plan = replace(make_plan(cfg), lanes=lanes)
        check_checkpoints(cfg, {h.name: plan.heads[h.name]})
        box = next(m for m in mailboxes(plan, cfg.mode == "process") if m["name"] == f"out.{h.name}")
        check_preallocation([box])
        ring = SlotRing.create(**box)
        renames = lanes.seat_renames(seats[0], h.name)
        assert res.control is not None and res.runner is not None and res.governor is not None
        try:
            _rename(engine, renames, clear=False)
            for lane in lanes.of(h.name):
                res.control.set_rate(lane.entry, lane.rate_hz)
            res.rings[ring.name] = ring
            engine._handoffs.add_head(h.name, ring)
            res.runner.add(head_spec(plan, res.rings, h.name, cfg.model_dump(mode="json")), ring)
        except BaseException:
            engine._handoffs.remove_head(h.name)
            res.rings.pop(ring.name, None)
            _rename(engine, {new: old for old, new in renames.items()}, clear=True)
            ring.close()
            raise
        model = plan.heads[h.name]
        engine.boundary.add_head(h.name, model.meta, model.output_spec, h.output.grid == "native")
        engine._outbox.add_head(h.name, model, ring, lanes)
        engine._seats[h.name] = seats[0]
        engine.config, engine.plan = cfg, plan
        res.governor.relane(cfg, lanes)
        log.info("head %r (%s) added, in seat %s", h.name, h.model, seats[0])
        return h.name


def remove_head(engine: Engine, name: str) -> None:
    engine._require_running()
    res = engine._res
    with _LOCK:
        heads = list(engine.plan.heads)
        if name == "foundation":
            raise ValueError("the foundation model serves every head: stop the engine instead of removing it")
        if name not in heads:
            raise KeyError(f"no head named {name!r}; heads: {heads}")
        if len(heads) == 1:
            raise ValueError(f"{name!r} is the engine's last head: stop the engine instead of removing it")
        assert res.control is not None and res.runner is not None and res.governor is not None
        ring = res.rings[f"out.{name}"]
        for thread in res.runner.remove(name):
            res.fence.hold_until_gone(thread)
        raw = engine.config.model_dump(mode="json")
        cfg = load_config({**raw, "heads": [x for x in raw["heads"] if x["name"] != name]})
        seat = engine._seats.pop(name, None)
        renames = _seat_back(engine.lanes, res.control.index, name, seat)
        lanes = make_lanes(cfg, tuple(sorted([*engine.lanes.seats, *([seat] if seat else [])], key=_seat_order)))
        plan = replace(engine.plan, cfg=cfg, heads={h: m for h, m in engine.plan.heads.items() if h != name})
        plan = replace(plan, lanes=lanes)
        engine._outbox.remove_head(name, lanes)
        engine.boundary.remove_head(name)
        engine._handoffs.remove_head(name)
        engine.config, engine.plan = cfg, plan
        res.governor.relane(cfg, lanes)
        _rename(engine, renames, clear=True)
        res.rings.pop(ring.name, None)
        res.fence.defer(ring.close)  # once no call in flight holds it (Note [Unmapping at stop])
        _free_device_memory(engine.config)
        log.info("head %r removed%s", name, f", seat {seat} free again" if seat else "")


def _seat_order(seat: str) -> int:
    return int(seat.lstrip("+"))


def _seat_back(lanes: Lanes, taken: Mapping[str, int], name: str, seat: str | None) -> dict[str, str]:
    """Where a removed head's entries and readers go: back to its seat, or (a head of the config, which has none)
    to names no model can have, retired (``taken``: the names in use)."""
    if seat is not None:
        return {new: old for old, new in lanes.seat_renames(seat, name).items()}
    k = 1
    while f"~{k}:{name}" in taken:
        k += 1
    return {n: f"~{k}:{n}" for n in dict.fromkeys([name, *(lane.entry for lane in lanes.of(name))])}


def _free_device_memory(cfg: EngineConfig) -> None:
    """Thread mode on CUDA: the removed head's model and graphs were its thread's; hand their memory back to the
    driver (a process-mode worker's went with its process)."""
    if cfg.mode == "thread" and cfg.device.startswith("cuda"):
        import torch

        gc.collect()
        torch.cuda.empty_cache()
