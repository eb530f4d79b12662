"""Thread mode: every model in its own thread (and CUDA stream) of one process, same loop as process mode."""

from __future__ import annotations

import logging
import queue
import threading
import time

from vpengine.runtime.control import POLL_S, STOPPED
from vpengine.runtime.handoff import Handoffs
from vpengine.runtime.supervisor import EngineStartError, Runner
from vpengine.runtime.worker import describe_exception, prepare_worker

log = logging.getLogger("vpengine.threads")


class ThreadRunner(Runner):
    def __init__(  # type: ignore[no-untyped-def]
        self, *args, handoffs: Handoffs | None = None, **kw
    ) -> None:
        super().__init__(*args, **kw)
        # what the workers hand each other on the device and the submitting thread (handoff.py)
        self.handoffs = handoffs or Handoffs()
        self._threads: dict[str, threading.Thread] = {}
        self._events: queue.Queue[tuple[str, str, str]] = (
            queue.Queue()
        )  # (name, "ready"|"error"|"exit", text)
        self._generation: dict[str, int] = dict.fromkeys(self.specs, 0)
        self._monitor: threading.Thread | None = None

    def _should_stop(self, name: str, gen: int) -> bool:
        return self._stopping or self.control.stopping or self._generation[name] != gen

    def _main(self, name: str, gen: int) -> None:
        spec = self.specs[name]
        try:
            core = prepare_worker(
                spec,
                self.rings[spec.in_ring.name],
                self.rings[spec.out_ring.name],
                self.control,
                own_process=False,
                handoff=self.handoffs.for_worker(name),
            )
        except BaseException as e:
            self._events.put((name, "error", describe_exception(name, e)))
            return
        self._events.put((name, "ready", ""))
        try:
            core.run(lambda: self._should_stop(name, gen))
        except BaseException as e:
            text = describe_exception(name, e)
            self.control.add(name, "errors")
            self.control.set_error(name, text)
            self._events.put((name, "exit", text))
            return
        self._events.put((name, "exit", ""))

    def _launch(self, name: str) -> None:
        self._generation[name] += 1
        t = threading.Thread(
            target=self._main, args=(name, self._generation[name]), name=f"vpengine-{name}", daemon=True
        )
        self._threads[name] = t
        t.start()

    def start(self) -> None:
        import torch

        if self.cfg.device == "cpu":
            # Intra-op threads are per process: in thread mode all models share one pool, sized like a worker's.
            torch.set_num_threads(self.cfg.foundation_model.cpu_threads)
        for name in self.specs:
            self._launch(name)
        waiting = set(self.specs)
        deadline = time.monotonic() + self.cfg.runtime.ready_timeout_s
        errors = []
        while waiting:
            try:
                name, kind, text = self._events.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                self.stop()
                raise EngineStartError(
                    f"workers {sorted(waiting)} were not ready within {self.cfg.runtime.ready_timeout_s} s"
                ) from None
            waiting.discard(name)
            if kind != "ready":
                errors.append(text or f"{name} exited during start-up")
        if errors:
            self.stop()
            raise EngineStartError("worker start-up failed:\n" + "\n".join(errors))
        self._monitor = threading.Thread(target=self._watch, name="vpengine-monitor", daemon=True)
        self._monitor.start()

    def _watch(self) -> None:
        while not self._stopping:
            timeout = min(self._run_due_restarts(), POLL_S)
            try:
                name, kind, text = self._events.get(timeout=max(0.01, timeout))
            except queue.Empty:
                continue
            if kind == "exit" and not self._stopping:
                first_line = text.splitlines()[0] if text else "exited"
                self._on_exit(name, crashed=bool(text), reason=first_line)
            elif kind == "error" and not self._stopping:
                self._on_exit(name, crashed=True, reason=text.splitlines()[0])

    def stop(self) -> list[str]:
        with self._lock:
            self._stopping = True
        self.control.request_stop()
        for ring in self.rings.values():
            ring.wake_all()
        if self.handoffs.inline is not None:
            self.handoffs.inline.wake()  # an armed foundation worker disarms and sees the stop
        deadline = time.monotonic() + self.cfg.runtime.stop_timeout_s
        abandoned = []
        for name, t in self._threads.items():
            t.join(max(0.0, deadline - time.monotonic()))
            if t.is_alive():
                abandoned.append(name)
            else:
                self.control.set_state(name, STOPPED)
        if self._monitor is not None:
            self._monitor.join(2.0)
        if abandoned:
            log.error(
                "threads %s did not stop within %.1f s; abandoned (daemon threads)",
                abandoned,
                self.cfg.runtime.stop_timeout_s,
            )
        return abandoned
