"""Heads that misbehave on purpose, loaded by workers through the 'package.module:Class' route users have."""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import threading
import time
from pathlib import Path

import torch

from vpengine.models.base import BuildContext, Model, Options
from vpengine.models.tiny import TinyDepthHead, TinyHeadOptions, TinyViT, TinyViTOptions

#: Set by a test that is done with a slow build (``build_s``) of a head in its own process: the build ends there, so
#: the thread left building does not outlive the test. While it builds it holds models.build's ``build_lock``, which
#: every build and plan of the process takes: the next tests' engines would time out waiting for it.
BUILDS_RELEASED = threading.Event()
BUILDS_STARTED = threading.Event()  # set when a slow build (build_s, not planning's) has begun waiting


class FaultOptions(Options):
    raise_at_run: int | None = None  # raise on this run (1-based) of this process
    raise_every: int | None = None  # raise on every Nth run (a model that fails on some frames)
    cuda_error: bool = False  # raise_at_run raises a CUDA error (Note [Frame errors]: its worker is restarted)
    once_marker: str | None = None  # if set, raise, exit or hang only while this file does not exist (touched first)
    hang_at_run: int | None = None  # sleep for ever (or hang_s) on this run and later ones (once, with once_marker)
    hang_s: float | None = None  # how long a hang lasts; None: for ever
    exit_at_run: int | None = None  # os._exit(0) on this run (once, with once_marker)
    gil_hang_at_run: int | None = None  # on this run, sleep for ever in C code that holds the GIL
    ignore_sigterm: bool = False
    sleep_ms: float = 0.0  # every run takes at least this long
    stall_every: int | None = None  # every Nth run also sleeps stall_ms (a transient lag)
    stall_ms: float = 0.0
    fail_build: bool = False
    build_s: float = 0.0  # building takes this long (a head that compiles), or until BUILDS_RELEASED is set
    log_at_build: str | None = None  # log this (at log_at_build_level, logger vpengine.faulty) when built
    log_at_build_level: str = "WARNING"


class _Runs:
    """Counts a model's runs on served frames: not the engine's calls before READY, which give the model its example
    inputs (the executor's warm-up, the first call; on CUDA also each worker's first batch, Note [First batch] in
    runtime/worker.py, every frame of it the example). On the eager backend: compiled, ``forward`` is traced, not
    called per frame."""

    calls = 0
    _example: dict | None = None

    def _run(self, inputs) -> int | None:  # type: ignore[no-untyped-def]
        """This call's run number (1-based), or None for a warm-up call."""
        if self._example is None:
            self._example = {k: v[0].detach().clone() for k, v in inputs.items()}
            return None
        if all(k in inputs and torch.equal(inputs[k][0], v) for k, v in self._example.items()):
            return None
        self.calls += 1
        return self.calls


class FaultyHead(_Runs, TinyDepthHead):
    """tiny_depth with injectable faults."""

    def __init__(self, ctx: BuildContext, fault: FaultOptions) -> None:
        super().__init__(ctx, TinyHeadOptions())
        self.fault = fault
        if fault.ignore_sigterm and not ctx.plan_only:
            signal.signal(signal.SIGTERM, signal.SIG_IGN)

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        fault = ctx.options(FaultOptions)
        if fault.fail_build and not ctx.plan_only:
            raise RuntimeError("injected build failure")
        if fault.build_s and not ctx.plan_only:
            BUILDS_STARTED.set()
            BUILDS_RELEASED.wait(fault.build_s)
        if fault.log_at_build and not ctx.plan_only:
            logging.getLogger("vpengine.faulty").log(
                logging.getLevelName(fault.log_at_build_level), "%s", fault.log_at_build
            )
        return cls(ctx, fault)

    def forward(self, inputs):
        run = self._run(inputs)
        if run is None:
            return super().forward(inputs)
        f = self.fault
        if f.sleep_ms:
            time.sleep(f.sleep_ms / 1000)
        if f.stall_every and run % f.stall_every == 0:
            time.sleep(f.stall_ms / 1000)
        first_time = f.once_marker is None or not Path(f.once_marker).exists()
        if f.raise_at_run is not None and run == f.raise_at_run and first_time:
            if f.once_marker is not None:
                Path(f.once_marker).touch()
            raise RuntimeError(
                f"{'CUDA error: ' if f.cuda_error else ''}injected failure at run {run} (pid {os.getpid()})"
            )
        if f.raise_every and run % f.raise_every == 0:
            raise ValueError(f"injected failure on every {f.raise_every}th run")
        if f.exit_at_run is not None and run == f.exit_at_run and first_time:
            if f.once_marker is not None:
                Path(f.once_marker).touch()
            os._exit(0)
        if f.gil_hang_at_run is not None and run == f.gil_hang_at_run:
            ctypes.PyDLL(None).sleep(100000)  # a PyDLL call keeps the GIL: no other thread of ours runs
        if f.hang_at_run is not None and run >= f.hang_at_run and first_time:
            if f.once_marker is not None:
                Path(f.once_marker).touch()
            if f.hang_s is not None:
                time.sleep(f.hang_s)
            else:
                while True:
                    time.sleep(3600)
        return super().forward(inputs)


class FaultyViTOptions(TinyViTOptions):
    raise_at_run: int | None = None  # raise on this run (1-based) of this worker
    cuda_error: bool = False  # raise a CUDA error (Note [Frame errors]: its worker is restarted)
    once_marker: str | None = None  # if set, raise only while this file does not exist (it is created first)


class FaultyViT(_Runs, TinyViT):
    """tiny_vit (same weights for the same seed) that raises once on a given run: a foundation model to restart."""

    options_type = FaultyViTOptions

    def __init__(self, image_hw: tuple[int, int], opts: FaultyViTOptions, dtype: str = "float32") -> None:
        super().__init__(image_hw, opts, dtype)
        self.fault = opts

    def forward(self, inputs):
        run = self._run(inputs)
        f = self.fault
        if run is not None and run == f.raise_at_run and (f.once_marker is None or not Path(f.once_marker).exists()):
            if f.once_marker is not None:
                Path(f.once_marker).touch()
            raise RuntimeError(f"{'CUDA error: ' if f.cuda_error else ''}injected foundation failure at run {run}")
        return super().forward(inputs)
