"""Building a worker: its model on its device, warmed up before READY, and its loop (``worker.py``) around it.

Runs in the worker's thread (thread mode) or child process (process mode), so the model is built where it runs.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable

import torch

from vpengine.models.base import check_outputs
from vpengine.models.build import build_lock, build_model
from vpengine.runtime.control import ControlBlock
from vpengine.runtime.device import DeviceContext
from vpengine.runtime.handoff import WorkerHandoff, inline_wanted
from vpengine.runtime.worker import WorkerCore, WorkerSpec, input_keys
from vpengine.transport.ring import SlotRing

log = logging.getLogger("vpengine.worker")

_register_lock = threading.Lock()


def _register_host_rings(*rings: SlotRing) -> None:
    """Page-lock host mailboxes this process copies to or from, so the copies run asynchronously on our stream.

    Registration is per process (it pins this process's mapping), so every worker does it for its own rings.
    """
    from vpengine.transport.memory import HostRegion

    with _register_lock:
        for ring in rings:
            region = ring.data_region
            if isinstance(region, HostRegion) and not region.cuda_registered:
                region.register_with_cuda()


def warms_first_batch(dev: DeviceContext) -> bool:
    """Whether a worker runs a batch of a frame per camera before READY (Note [First batch] in worker.py): on CUDA."""
    return dev.cuda


def prepare_worker(
    spec: WorkerSpec,
    in_ring: SlotRing,
    out_ring: SlotRing,
    control: ControlBlock,
    own_process: bool,
    handoff: WorkerHandoff | None = None,
    cancelled: Callable[[], bool] | None = None,
    beside_serving: bool = False,
    alone: bool = True,
) -> WorkerCore:
    """Build the model on its device, warm it up (allocations happen here, before READY), return its loop.

    ``cancelled``: whether the build is still wanted (a thread-mode engine that stopped, a head removed): checked while
    waiting for the build lock, and again when the warm-up's turn under it comes (Note [One build at a time]).
    ``beside_serving``: other workers of this process serve meanwhile (thread mode: a head added, a restart).
    ``alone``: no other model runs in this process (with ``own_process``; Note [Process groups] in process.py).
    """
    from vpengine.backends import make_executor
    from vpengine.runtime.control import LOADING, READY

    cfg = spec.engine_config()
    mcfg = cfg.model(spec.name)
    device = torch.device(cfg.device)
    if own_process:
        # A GPU worker needs no CPU thread pool: left at its default (one thread per core, in every worker), the
        # OpenMP threads spin after any small CPU op and burn cores for nothing.
        torch.set_num_threads(mcfg.cpu_threads)
    control.set_state(spec.name, LOADING)
    control.set(spec.name, "pid", os.getpid())

    def step(done: int, total: int) -> None:  # Note [Start progress] in supervisor.py
        control.set(spec.name, "build_done", done)
        control.set(spec.name, "build_total", total)
        control.heartbeat(spec.name)
        build_lock.step()

    step(0, 0)
    # the governor wrote it before any worker starts (Note [Stream priority at run time] in device.py)
    dev = DeviceContext(device, priority=int(control.get(spec.lanes[0].entry, "stream_level")))
    if dev.cuda:
        _register_host_rings(in_ring, out_ring)
        from vpengine.transport.cuda_vmm import mps_enabled

        try:
            mps: bool | None = bool(mps_enabled(device.index or 0))
        except Exception:  # the bindings are optional in thread mode; MPS status is informational
            mps = None  # not known: it may share the device
        control.set(spec.name, "mps_active", int(bool(mps)))
        # alone in a context of its own, its stream's priority ranks it against nothing: it never moves
        dev.moves = not (own_process and alone) or mps is not False
    if beside_serving and dev.cuda and mcfg.backend == "compile":
        from vpengine.backends.compiled import compile_workers_ready

        compile_workers_ready(cancelled=cancelled)  # Note [Compile workers]
    with dev.active():
        model = build_model(
            cfg, spec.name, spec.role, spec.upstream, spec.upstream_meta, device, plan_only=False, cancelled=cancelled
        )
        # Under the build lock too: a CUDA graph capture (compile backend) must not overlap another thread building
        # a model, whose layer init draws from the CUDA RNG that the capture has claimed (seen on an H100).
        what = f"model {spec.name!r} of engine {cfg.name!r} (warm-up)"
        with build_lock.held(what, cfg.runtime.ready_timeout_s, cancelled):
            executor = make_executor(
                model,
                mcfg.backend,
                device,
                spec.name,
                options=mcfg.backend_options,
                precision=mcfg.precision or cfg.precision,
                max_batch=len(spec.lanes),  # Note [Cameras]: a frame of each camera at once
                progress=step,
            )
            # Warm-up on random inputs: first-run allocations, autotuning and compilation all happen before READY,
            # so the steady state allocates nothing (Invariant: constant memory).
            with torch.inference_mode():
                check_outputs(spec.name, model.output_spec, executor(model.example_inputs(device)))
                keys = input_keys(spec, in_ring)
                bound = executor.bind([{k: v[k] for k in keys} for v in in_ring.views], list(out_ring.views))
            if handoff is not None and not inline_wanted(dev.cuda, bound):
                handoff = WorkerHandoff(handoff.in_events, handoff.out_events, None)  # Note [Inline launch]
            # Its batch buffers under the lock too: another model's capture counts its graph pool by what the
            # device reserved meanwhile (CompiledExecutor.held_bytes).
            core = WorkerCore(
                spec, executor, model.output_spec, in_ring, out_ring, control, dev, bound=bound, handoff=handoff
            )
            if warms_first_batch(dev):
                core.warm_batch(model.example_inputs(device))
        dev.complete()
    # a process of its own: all it reserved is the model's; beside other models, what it holds alone
    try:
        held = dev.memory_bytes() if own_process and alone else executor.held_bytes() + core.buffer_bytes()
    except Exception as e:  # a statistic: never a reason to fail a start
        log.warning("%s: its device memory could not be counted (%s); stats() shows 0", spec.name, e)
        held = 0
    control.set(spec.name, "device_mem_bytes", held)
    control.set(spec.name, "started_at", time.monotonic())
    control.heartbeat(spec.name)
    control.set_state(spec.name, READY)
    return core
