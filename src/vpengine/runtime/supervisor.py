"""Supervision shared by the thread and process runners: READY, death, restart with backoff, stop.

A runner owns one worker per model. When a worker dies (an exception in its model, SIGKILL, a hang that the
runner killed), the runner releases the pins it held in its input ring and forgets any slot it left half-written
in its output ring, so the models next to it never block; then it restarts the worker after a backoff that doubles
each time, up to ``runtime.max_restarts``, after which the model is marked ``failed`` in ``stats()`` and the rest
of the engine goes on without it.
"""

from __future__ import annotations

import logging
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass

from vpengine.config import EngineConfig
from vpengine.runtime.control import FAILED, RESTARTING, ControlBlock
from vpengine.runtime.worker import WorkerSpec
from vpengine.transport.ring import SlotRing

log = logging.getLogger("vpengine.supervisor")

#: The longest wait before a restart: the delay doubles from runtime.restart_backoff_s up to this.
RESTART_BACKOFF_MAX_S = 10.0


class EngineStartError(RuntimeError):
    """A worker failed to load or warm up; the message carries the worker's own traceback."""


class EngineDeadError(RuntimeError):
    """The engine was stopped or its foundation model has failed for good; it cannot serve."""


@dataclass
class _Restart:
    due: float
    attempt: int


class Runner(ABC):
    def __init__(
        self, specs: list[WorkerSpec], rings: dict[str, SlotRing], control: ControlBlock, cfg: EngineConfig
    ) -> None:
        self.specs = {s.name: s for s in specs}
        self.rings = rings
        self.control = control
        self.cfg = cfg
        self._lock = threading.RLock()
        self._stopping = False
        self._restarts: dict[str, int] = {s.name: 0 for s in specs}
        self._pending: dict[str, _Restart] = {}

    # --------------------------------------------------------------------------------------- interface
    @abstractmethod
    def start(self) -> None:
        """Start every worker and wait until all are READY (or raise EngineStartError)."""

    @abstractmethod
    def stop(self) -> list[str]:
        """Stop every worker; always returns. Returns names of workers that had to be killed or abandoned."""

    @abstractmethod
    def _launch(self, name: str) -> None:
        """(Re)start one worker without waiting for READY."""

    @property
    def stopping(self) -> bool:
        return self._stopping

    def alive(self, name: str) -> bool:
        return self.control.state(name) not in ("failed", "stopped")

    # ------------------------------------------------------------------------------------- death handling
    def _cleanup_after(self, name: str) -> None:
        """Release what a dead worker held so its neighbours never wait on it."""
        spec = self.specs[name]
        in_ring = self.rings[spec.in_ring.name]
        out_ring = self.rings[spec.out_ring.name]
        in_ring.release_reader(spec.in_reader)
        out_ring.reset_writer()

    def _on_exit(self, name: str, crashed: bool, reason: str) -> None:
        """Called by the runner's monitor when a worker is gone."""
        with self._lock:
            self._cleanup_after(name)
            if self._stopping:
                return
            if crashed:
                self.control.add(name, "crashes")
            n = self._restarts[name]
            limit = self.cfg.runtime.max_restarts
            if n >= limit:
                self.control.set_state(name, FAILED)
                log.error("%s failed for good after %d restarts: %s", name, n, reason)
                return
            delay = min(self.cfg.runtime.restart_backoff_s * (2**n), RESTART_BACKOFF_MAX_S)
            self._pending[name] = _Restart(time.monotonic() + delay, n + 1)
            self.control.set_state(name, RESTARTING)
            log.warning("%s stopped (%s); restart %d/%d in %.1f s", name, reason, n + 1, limit, delay)

    def _run_due_restarts(self) -> float:
        """Launch restarts whose time has come; return seconds until the next one (inf if none)."""
        with self._lock:
            now = time.monotonic()
            nxt = float("inf")
            for name, r in list(self._pending.items()):
                if self._stopping:
                    self._pending.clear()
                    break
                if r.due <= now:
                    del self._pending[name]
                    self._restarts[name] = r.attempt
                    self.control.add(name, "restarts")
                    try:
                        self._launch(name)
                    except Exception as e:  # a failed launch counts as a crash
                        log.error("%s could not be restarted: %s", name, e)
                        self._on_exit(name, True, f"restart failed: {e}")
                else:
                    nxt = min(nxt, r.due - now)
            return nxt
