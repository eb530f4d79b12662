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

import contextlib
import logging
import threading
from collections.abc import Mapping
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import yaml

from vpengine.config import ConfigError, EngineConfig, HeadConfig, load_config, load_yaml
from vpengine.models.base import ModelBuildError
from vpengine.models.build import BuildCancelled
from vpengine.models.registry import resolve
from vpengine.models.weights import check_checkpoints
from vpengine.runtime.lanes import Lanes, make_lanes
from vpengine.runtime.plan import Plan, check_preallocation, mailboxes, make_plan
from vpengine.runtime.supervisor import EngineDeadError, EngineStartError
from vpengine.runtime.worker import WorkerSpec
from vpengine.transport.ring import SlotRing

if TYPE_CHECKING:
    from vpengine.engine.core import Engine

log = logging.getLogger("vpengine")


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
        try:  # the config file's loader: a key given twice is refused here too
            data = load_yaml(head, "the head's config", "the head's config")
        except yaml.YAMLError as e:
            raise ConfigError(f"a head's config is YAML (or JSON) text; this one does not parse: {e}") from None
        if not isinstance(data, dict):
            raise ConfigError(f"a head's config is a mapping (name: ..., model: ...); got {head!r}")
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
    runner = engine._res.runner
    # planning too: it builds the head on the meta device (Note [Building beside serving threads] in threads.py)
    with runner.beside_serving() if runner is not None else contextlib.nullcontext():
        return _add_head(engine, head)


def _add_head(engine: Engine, head: HeadConfig | dict[str, Any] | str) -> str:
    res = engine._res
    with engine._heads_lock:
        raw = engine.config.model_dump(mode="json")
        cfg = load_config({**raw, "heads": [*raw["heads"], _head_data(head)]})
        h = cfg.heads[-1]
        names = cfg.process_mates(h.name)[:-1]  # the new head comes last
        if names:
            raise ConfigError(
                f"head {h.name!r}: process {h.process!r} is the running process of {names}; a head added at run "
                "time gets a process of its own (process: null, or a name no model has)"
            )
        if h.input_mode == "fifo":
            raise ConfigError(f"head {h.name!r}: input_mode fifo is for heads configured at start; add it as latest")
        try:  # a model that does not exist is named before the room for it is counted
            resolve(h.model, "head")
        except ModelBuildError as e:
            if e.__cause__ is not None:  # the user's module itself failed as it was imported: its own error
                raise EngineStartError(f"head {h.name!r} cannot be added: {e}") from e
            raise ConfigError(f"heads.{h.name}.model: {e}") from None  # its model field names no model
        seats = engine.lanes.seats
        if not seats:
            raise RuntimeError(
                f"no room for head {h.name!r}: runtime.spare_heads is {engine.config.runtime.spare_heads} and every "
                "seat is taken by a head added earlier; remove one, or start the engine with more spare heads"
            )
        lanes = make_lanes(cfg, seats[1:])
        try:  # waits for the build lock while other builds run: not past a stop (Note [One build at a time])
            plan = replace(make_plan(cfg, cancelled=lambda: res.runner is None or res.runner.stopping), lanes=lanes)
            model = plan.heads[h.name]
            check_checkpoints(cfg, {h.name: model})
        except BuildCancelled:
            raise EngineDeadError(f"engine stopped while {h.name} was being added") from None
        except (ConfigError, EngineStartError, EngineDeadError):
            raise
        except ModelBuildError as e:  # a reason of its own, in one line (a missing checkpoint, bad options)
            raise EngineStartError(f"head {h.name!r} cannot be added: {e}") from e.__cause__
        except Exception as e:  # a user class's own error: its traceback says where
            raise EngineStartError(f"head {h.name!r} cannot be added: {type(e).__name__}: {e}") from e
        box = next(m for m in mailboxes(plan, cfg.mode == "process") if m["name"] == f"out.{h.name}")
        check_preallocation([box])
        control, runner, governor = res.control, res.runner, res.governor
        if control is None or runner is None or governor is None:
            raise EngineDeadError("engine is stopped")
        renames = lanes.seat_renames(seats[0], h.name)
        ring = SlotRing.create(**box)
        started = False
        try:
            _rename(engine, renames, clear=False)
            for lane in lanes.of(h.name):
                control.set_rate(lane.entry, lane.rate_hz)
            governor.seat(cfg, lanes)  # its priorities and stream level before its worker reads them
            res.rings[ring.name] = ring
            engine._handoffs.add_head(h.name, ring)
            engine.boundary.add_head(h.name, model.meta, model.output_spec, h.output.grid == "native")
            started = True
            runner.add(head_spec(plan, res.rings, h.name, cfg.model_dump(mode="json")), ring)
            engine._require_running()  # stopped while it warmed up: nothing to attach it to
            engine._outbox.add_head(h.name, model, ring, lanes)
        except BaseException:
            left = runner.remove(h.name) if started else []
            engine.boundary.remove_head(h.name)
            engine._handoffs.remove_head(h.name)
            _give_back(engine, {new: old for old, new in renames.items()}, h.name, ring, left)
            governor.unseat()  # the others' stream levels as they were
            raise
        engine._seats[h.name] = seats[0]
        engine.config, engine.plan = cfg, plan
        governor.relane(cfg, lanes)
        log.info("head %r (%s) added, in seat %s", h.name, h.model, seats[0])
        return h.name


def remove_head(engine: Engine, name: str) -> None:
    engine._require_running()
    res = engine._res
    with engine._heads_lock:
        heads = list(engine.plan.heads)
        if name == "foundation":
            raise ValueError("the foundation model serves every head: stop the engine instead of removing it")
        if name not in heads:
            raise KeyError(f"no head named {name!r}; heads: {heads}")
        if len(heads) == 1:
            raise ValueError(f"{name!r} is the engine's last head: stop the engine instead of removing it")
        others = [m for m in engine.config.process_mates(name) if m != name]
        if others:
            raise ValueError(
                f"{name!r} shares process {engine.config.head(name).process!r} with {others}: a head that shares its "
                "worker process cannot be removed while the engine runs"
            )
        control, runner, governor = res.control, res.runner, res.governor
        if control is None or runner is None or governor is None:
            raise EngineDeadError("engine is stopped")
        ring = res.rings[f"out.{name}"]
        left = runner.remove(name)
        raw = engine.config.model_dump(mode="json")
        cfg = load_config({**raw, "heads": [x for x in raw["heads"] if x["name"] != name]})
        seat = engine._seats.pop(name, None)
        back = _seat_back(engine.lanes, control.index, name, seat, retire=bool(left))
        freed = (seat,) if seat is not None and not left else ()
        lanes = make_lanes(cfg, tuple(sorted([*engine.lanes.seats, *freed], key=_seat_order)))
        heads_left = {h: m for h, m in engine.plan.heads.items() if h != name}
        plan = replace(engine.plan, cfg=cfg, heads=heads_left, lanes=lanes)
        engine._outbox.remove_head(name, lanes)
        engine.boundary.remove_head(name)
        engine._handoffs.remove_head(name)
        engine.config, engine.plan = cfg, plan
        governor.relane(cfg, lanes)
        _give_back(engine, back, name, ring, left)
        log.info("head %r removed%s", name, f", seat {seat} free again" if freed else "")


def _give_back(
    engine: Engine, renames: dict[str, str], name: str, ring: SlotRing, left: list[threading.Thread]
) -> None:
    """What a head held goes back: its entries and readers cleared and renamed (to its seat, or retired), its output
    mailbox unmapped once no call in flight and no thread left behind (``left``: a thread-mode worker that did not
    stop) can hold it; then its device memory."""
    res = engine._res
    res.rings.pop(ring.name, None)
    if not left:
        _rename(engine, renames, clear=True)

    def close() -> None:
        ring.close()
        _free_device_memory(engine.config)

    def after_threads() -> None:
        for t in left:
            t.join()
        res.fence.defer(close)

    if left:  # its seat stays retired (renamed away from the head's names, never cleared: the thread may write)
        _rename(engine, renames, clear=False)
        threading.Thread(target=after_threads, name=f"vpengine-unmap-{name}", daemon=True).start()
    else:
        res.fence.defer(close)  # Note [Unmapping at stop]: once no call in flight holds it


def _seat_order(seat: str) -> int:
    return int(seat.lstrip("+"))


def _seat_back(lanes: Lanes, taken: Mapping[str, int], name: str, seat: str | None, retire: bool) -> dict[str, str]:
    """Where a removed head's entries and readers go: back to its seat, or (a head of the config, which has none,
    or ``retire``: one whose worker thread is still there) to names no model can have, retired (``taken``: the names
    in use)."""
    if seat is not None and not retire:
        return {new: old for old, new in lanes.seat_renames(seat, name).items()}
    k = 1
    while f"~{k}:{name}" in taken:
        k += 1
    return {n: f"~{k}:{n}" for n in dict.fromkeys([name, *(lane.entry for lane in lanes.of(name))])}


def _free_device_memory(cfg: EngineConfig) -> None:
    """Thread mode on CUDA: the removed head's model and graphs were its thread's; hand their memory back to the
    driver (a process-mode worker's went with its process). They are garbage once its thread has ended, by reference
    counting alone (tests/integration/test_heads_at_run_time.py): no garbage collection here, which would stop every
    serving thread while it walks the heap (Note [Building beside serving threads] in runtime/threads.py)."""
    if cfg.mode == "thread" and cfg.device.startswith("cuda"):
        import torch

        torch.cuda.empty_cache()
