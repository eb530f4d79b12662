"""What ``Engine.stats()`` and ``Engine.memory_report`` say about the models and the mailboxes, read from the control
block and the rings (shared memory; no logs parsed)."""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import torch

from vpengine.runtime.control import ControlBlock

if TYPE_CHECKING:
    from vpengine.engine.core import Engine
from vpengine.runtime.lanes import Lanes
from vpengine.transport.ring import SlotRing


def model_stats(
    lanes: Lanes, ctl: ControlBlock, rings: Mapping[str, SlotRing]
) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """Each model's counters, rates and latencies over its lanes, and with several cameras each camera's, per model
    (Note [Cameras] in runtime/worker.py)."""
    models: dict[str, Any] = {}
    per_camera: dict[str, dict[str, Any]] = {}
    for name, mine in lanes.by_model.items():
        several = not mine[0].only
        try:
            snap = ctl.snapshot(name, cameras=[lane.entry for lane in mine] if several else None)
            readers = rings["input" if name == "foundation" else "features"].stats()["readers"]
            reads = [readers[lane.reader] for lane in mine]  # type: ignore[index]
        except KeyError:  # a head removed while these stats were read (Note [Heads at run time])
            continue
        snap["frames_seen"] = sum(r["reads"] + r["missed"] for r in reads)
        snap["pending"] = sum(r["pending"] for r in reads)
        models[name] = snap
        if several:
            for lane, r in zip(mine, reads):
                one = ctl.snapshot(lane.entry)
                one["frames_seen"], one["pending"] = r["reads"] + r["missed"], r["pending"]
                one["entry"] = lane.entry  # its name in rate commands and summaries
                per_camera.setdefault(lane.camera, {})[name] = one
    return models, per_camera


def memory_report(rings: Mapping[str, SlotRing], ctl: ControlBlock | None, device: torch.device) -> dict[str, Any]:
    """The mailboxes' sizes and where they live, and on CUDA what the driver says each process holds (contexts
    included); ``stats()`` adds each model's device memory as it is then (``models_device_bytes``)."""
    per: dict[str, dict[str, Any]] = {
        n: {
            "bytes": r.layout.total_bytes,
            "slots": r.n_slots,
            "slot_bytes": r.layout.slot_bytes,
            "location": str(r.data_region.device),
        }
        for n, r in rings.items()
    }
    host = sum(v["bytes"] for v in per.values() if v["location"] == "cpu")
    dev = sum(v["bytes"] for v in per.values() if v["location"] != "cpu")
    report: dict[str, Any] = {
        "mailboxes": per,
        "mailbox_host_bytes": host,
        "mailbox_device_bytes": dev,
    }
    if device.type == "cuda" and ctl is not None:
        from vpengine.runtime.gpu import process_memory

        by_pid = process_memory(device.index or 0)  # as the driver reports it (contexts included)
        if by_pid:
            procs = processes({n: int(ctl.get(n, "pid")) for n in ctl.names})
            report["driver_bytes"] = {names: by_pid.get(p) for p, names in procs.items()}
    return report


def processes(pids: Mapping[str, int]) -> dict[int, str]:
    """pid -> a name for it: the models it runs joined by ``+`` (Note [Process groups] in runtime/process.py), so a
    process's figures are given once, under all its models; this process is ``engine (parent)`` (thread mode's
    models too). Models without a process yet (pid 0) are left out."""
    out: dict[int, list[str]] = {}
    for name, pid in pids.items():
        if pid and pid != os.getpid():
            out.setdefault(pid, []).append(name)
    return {p: "+".join(names) for p, names in out.items()} | {os.getpid(): "engine (parent)"}


def engine_stats(engine: Engine) -> dict[str, Any]:
    """``Engine.stats()`` of a running engine (the caller is inside its fence)."""
    res = engine._res
    ctl, rings, cfg, inline = res.control, res.rings, engine.config, engine._handoffs.inline
    assert ctl is not None
    models, per_camera = model_stats(engine.lanes, ctl, rings)
    return {
        "engine": {
            "state": engine._state,
            "mode": cfg.mode,
            "device": cfg.device,
            "uptime_s": time.monotonic() - engine._t_start,
            "submitted": engine._submitted,
            "rejected": engine._rejected,
            # Note [Inline launch]: frames whose foundation work the submitting thread queued
            "launched_by_submit": inline.launches if inline else 0,
            "mps": {
                "setting": cfg.mps,
                "daemon": engine._cuda.mps_dir if engine._cuda else None,
                "workers_on_mps": [n for n, m in models.items() if m["mps"]],
            },
        },
        "models": models,
        "cameras": per_camera,
        "results": engine._outbox.stats(),
        "mailboxes": {n: r.stats() for n, r in list(rings.items())},
        # each model's device memory (its process's reserved bytes when it has one to itself, else what it holds
        # alone: Executor.held_bytes) as it is now: heads added, removed or restarted since the start
        "memory": engine.memory_report | {"models_device_bytes": {n: m["device_mem_bytes"] for n, m in models.items()}},
    }
