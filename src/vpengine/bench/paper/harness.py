"""What every experiment of ``vpengine bench paper`` shares: its configs, engines, baselines and timers.

A benchmark starts from one engine config (``configs/bench.yaml`` by default, with ``--set`` overrides applied, as
``vpengine run`` does) whose heads named ``depth``, ``seg`` and ``det`` are templates: an experiment with eight depth
heads clones the ``depth`` head eight times. Everything else about the engine (mode, device, backends, precision,
MPS, frame size) is the config's, so a benchmark measures exactly what a user would run.

Latency is submit -> every head's result on the host with one frame in flight (lockstep), as in the paper. Frames are
synthetic scenes of the config's input size (content does not change the timing of dense models).
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vpengine.bench.common import event_ms

#: the head templates an experiment may clone, by kind
KINDS = ("depth", "seg", "det")


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


@dataclass
class Bench:
    """One benchmark's engine config and protocol.

    ``base`` is the validated config the experiments start from; ``frames`` is how many frames each lockstep
    measurement times; ``copy`` says whether the caller takes its own copies of results (``Engine.wait``'s
    ``copy``) or borrows read-only views of the output mailboxes.
    """

    base: Any
    frames: int = 100
    copy: bool = True
    config_path: str = ""
    overrides: list[str] = field(default_factory=list)

    @classmethod
    def load(
        cls, config: str, overrides: list[str] | tuple[str, ...] = (), frames: int = 100, copy: bool = True
    ) -> Bench:
        from vpengine.config import load_config

        return cls(load_config(config, list(overrides)), frames, copy, config, list(overrides))

    @property
    def device(self) -> str:
        return str(self.base.device)

    @property
    def on_cuda(self) -> bool:
        return self.device.startswith("cuda")

    @property
    def label(self) -> str:
        """How the engine ran, for log lines."""
        return f"{self.base.mode} mode, MPS {self.base.mps}, results {'copy' if self.copy else 'borrow'}"

    def head(self, kind: str, name: str, **extra: Any) -> dict[str, Any]:
        """The config's ``kind`` head (depth, seg or det) renamed ``name``, with ``extra`` fields set."""
        names = [h.name for h in self.base.heads]
        if kind not in names:
            where = f" ({self.config_path})" if self.config_path else ""
            raise ValueError(
                f"this experiment needs a head named {kind!r} to clone, and the config{where} has {names}; "
                f"name the template heads {', '.join(KINDS)}"
            )
        return {**self.base.head(kind).model_dump(), "name": name, **extra}

    def config(self, heads: list[dict[str, Any]], **top: Any) -> Any:
        """The base config with ``heads`` instead of its own and the top-level fields in ``top`` (mode, mps)."""
        from vpengine.config import load_config

        return load_config({**self.base.model_dump(), "heads": heads, **top})

    def setup(self) -> dict[str, Any]:
        """What ran, for the results file: the config as given and as resolved, and a digest the report labels."""
        b = self.base
        return {
            "config": self.config_path,
            "overrides": self.overrides,
            "device": b.device,
            "precision": b.precision,
            "mode": b.mode,
            "mps": b.mps,
            "height": b.input.height,
            "width": b.input.width,
            "backbone": b.foundation_model.model,
            "backend": b.foundation_model.backend,
            "heads": {h.name: {"model": h.model, "backend": h.backend} for h in b.heads},
            "results": "copy" if self.copy else "borrow",
            "frames": self.frames,
            "engine_config": b.model_dump(mode="json"),
        }

    def images(self, n: int = 8, size: tuple[int, int] | None = None) -> list[np.ndarray]:
        """``n`` synthetic frames of ``size`` (width, height; default: the config's input size)."""
        from vpengine.io.sources import SyntheticSource

        w, h = size or (self.base.input.width, self.base.input.height)
        src = SyntheticSource(w, h, 30.0, n)
        return [src.render(i * 3) for i in range(n)]


@contextlib.contextmanager
def mps_daemon() -> Iterator[str]:
    """The pipe directory of a reachable MPS daemon, or of a private one started here and stopped on exit; engines
    find it through $CUDA_MPS_PIPE_DIRECTORY meanwhile."""
    import os

    from vpengine.runtime import mps

    daemon = mps.find_daemon()
    started = None
    if daemon is None:
        started = mps.start()
        daemon = started["pipe_directory"]
    log(f"MPS daemon at {daemon} ({'started for this run' if started else 'already running'})")
    before = os.environ.get("CUDA_MPS_PIPE_DIRECTORY")
    os.environ["CUDA_MPS_PIPE_DIRECTORY"] = daemon
    try:
        yield daemon
    finally:
        if before is None:
            os.environ.pop("CUDA_MPS_PIPE_DIRECTORY", None)
        else:
            os.environ["CUDA_MPS_PIPE_DIRECTORY"] = before
        if started and started.get("started"):
            mps.stop(daemon)


# ------------------------------------------------------------------------------------------------ timing
def pct(values: list[float] | np.ndarray) -> dict[str, float]:
    """Percentiles and mean in ms of ``values`` in seconds."""
    a = np.asarray(values, dtype=float) * 1e3
    if not len(a):
        return {"p50": math.nan, "p90": math.nan, "p99": math.nan, "mean": math.nan, "n": 0}
    return {
        "p50": float(np.percentile(a, 50)),
        "p90": float(np.percentile(a, 90)),
        "p99": float(np.percentile(a, 99)),
        "mean": float(a.mean()),
        "n": len(a),
    }


def timed(step: Any, n: int, warmup: int = 10) -> dict[str, float]:
    """Latency percentiles (ms) and rate of ``step(i)`` for i in 0..n-1, after ``warmup`` untimed calls.

    A step that returns a float (a ``time.perf_counter`` reading) is timed from then: what came before is not its
    latency. Anything else a step returns is ignored.
    """
    for i in range(warmup):
        step(i)
    lat = []
    for i in range(n):
        t = time.perf_counter()
        start = step(i)
        lat.append(time.perf_counter() - (start if isinstance(start, float) else t))
    out = pct(lat)
    out["hz"] = 1e3 / out["mean"]
    return out


def lockstep(engine: Any, imgs: list[np.ndarray], b: Bench, warmup: int = 10, slot: bool = False) -> dict[str, float]:
    """submit -> all heads' results on the host, one frame in flight, ``b.frames`` times.

    ``slot``: the frame is written in place into the input mailbox (``Engine.frame_slot``), as a camera's decode
    would write it, and timed from the end of that write: the engine's latency without ``submit``'s copy.
    """

    def step(i: int) -> float | None:
        if not slot:
            engine.wait(engine.submit(imgs[i % len(imgs)]), timeout=120, copy=b.copy)
            return None
        with engine.frame_slot() as s:
            np.copyto(s.array, imgs[i % len(imgs)])
            t0 = time.perf_counter()
        engine.wait(s.frame_id, timeout=120, copy=b.copy)
        return t0

    for i in range(warmup):
        step(i)
    cpu = EngineCpu(engine)
    out = timed(step, b.frames, 0)
    out["cpu_cores"] = cpu.cores()
    return out


class EngineCpu:
    """CPU time of an engine's processes (this one and, in process mode, its workers) from construction to
    ``cores()``, in cores: CPU seconds per second of wall time."""

    def __init__(self, engine: Any) -> None:
        import os

        import psutil

        pids = {m["pid"] for m in engine.stats()["models"].values() if m.get("pid")} | {os.getpid()}
        self._procs = [psutil.Process(p) for p in pids]
        self._t0, self._c0 = time.monotonic(), self._seconds()

    def _seconds(self) -> float:
        total = 0.0
        for p in self._procs:
            try:
                t = p.cpu_times()
                total += t.user + t.system
            except Exception:  # a worker that restarted: its time is lost, not the run
                pass
        return total

    def cores(self) -> float:
        return (self._seconds() - self._c0) / max(time.monotonic() - self._t0, 1e-9)


@contextlib.contextmanager
def engines(cfgs: list[Any]) -> Iterator[list[Any]]:
    """Start several engines at once (in threads: their workers load in parallel), stop them all at the end."""
    from vpengine.engine import Engine

    es = [Engine(c) for c in cfgs]
    errors: list[BaseException] = []

    def start(e: Any) -> None:
        try:
            e.start()
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=start, args=(e,)) for e in es]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    try:
        if errors:
            raise errors[0]
        yield es
    finally:
        for e in es:
            e.stop()


# ------------------------------------------------------------------------------ the models without the engine
class InProcess:
    """The same models built in this process with no engine: the sequential baseline and the device-time floor."""

    def __init__(self, b: Bench, heads: list[dict[str, Any]], max_batch: int = 1) -> None:
        """``max_batch``: the largest batch of frames the models are built (and graph-captured) for, as an engine
        of that many cameras builds them (Note [Cameras] in runtime/worker.py)."""
        import torch

        from vpengine.backends import make_executor
        from vpengine.models.build import build_model
        from vpengine.runtime.plan import make_plan

        self.cfg = cfg = b.config(heads, mode="thread")
        self.device = torch.device(cfg.device)
        plan = make_plan(cfg)

        def executor(model: Any, mcfg: Any, name: str) -> Any:  # exactly as a worker builds it
            return make_executor(
                model,
                mcfg.backend,
                self.device,
                name,
                options=mcfg.backend_options,
                precision=mcfg.precision or cfg.precision,
                max_batch=max_batch,
            )

        fm = build_model(cfg, "foundation", "foundation", plan.frame_spec, {}, self.device, False)
        self.fm = executor(fm, cfg.foundation_model, "foundation")
        self.heads = {}
        self.graphed = {"foundation": cfg.foundation_model.backend == "compile"}
        for h in cfg.heads:
            m = build_model(cfg, h.name, "head", plan.features, plan.feature_meta, self.device, False)
            self.heads[h.name] = (executor(m, h, h.name), list(m.input_spec))
            self.graphed[h.name] = h.backend == "compile"
        self.torch = torch
        self._frame_runs: dict[int, dict[str, Any]] = {}

    def run(self, img: np.ndarray) -> dict[str, Any]:
        """Backbone once, then every head one after another, outputs copied to the host with ``.cpu()`` (pageable
        memory), as plain PyTorch code does."""
        torch = self.torch
        with torch.inference_mode():
            x = torch.from_numpy(img).to(self.device, non_blocking=True)[None]  # a batch of one frame
            feats = self.fm({"frame": x})
            outs = {}
            for name, (head, keys) in self.heads.items():
                out = head({k: feats[k] for k in keys})
                outs[name] = {k: v.cpu() for k, v in out.items()}
        return outs

    def latency(self, imgs: list[np.ndarray], n: int, warmup: int = 10) -> dict[str, float]:
        return timed(lambda i: self.run(imgs[i % len(imgs)]), n, warmup)

    def device_times(self, img: np.ndarray, n: int = 50, batch: int = 1) -> dict[str, float]:
        """Median device time (ms) of the backbone and of each head on a batch of ``batch`` copies of ``img``, each
        timed alone, with CUDA graphs where they capture (empty off CUDA)."""
        if self.device.type != "cuda":
            return {}
        parts = self._frame(img, batch)["parts"]
        with self.torch.inference_mode():
            return {name: event_ms(run, n) for name, run in parts.items()}

    def transfer_times(self, img: np.ndarray, n: int = 50) -> dict[str, float]:
        """Median device time (ms) of the copies a frame needs at least: the frame up from page-locked host memory,
        and every head's outputs down into page-locked host memory (CUDA events; empty off CUDA)."""
        if self.device.type != "cuda":
            return {}
        f = self._frame(img)
        with self.torch.inference_mode():
            return {name: event_ms(f[name], n) for name in ("upload", "download")}

    def chained_times(self, img: np.ndarray, n: int = 50) -> dict[str, float]:
        """Median device time (ms) of one frame's models run back to back on one stream and timed as one, without
        and with the frame's upload and the results' download (empty off CUDA). Unlike the sum of the models timed
        alone, each model here finds the caches as the one before it left them, as it does in the engine."""
        if self.device.type != "cuda":
            return {}
        f = self._frame(img)

        def whole() -> None:
            f["upload"]()
            f["back_to_back"]()
            f["download"]()

        with self.torch.inference_mode():
            return {"compute": event_ms(f["back_to_back"], n), "with_transfers": event_ms(whole, n)}

    def back_to_back_ms(self, img: np.ndarray, batch: int, n: int = 50) -> float:
        """Median device time (ms) of a batch of ``batch`` copies of ``img`` through every model back to back on one
        stream, no transfers (CUDA only)."""
        with self.torch.inference_mode():
            return event_ms(self._frame(img, batch)["back_to_back"], n)

    def _frame(self, img: np.ndarray, batch: int = 1) -> dict[str, Any]:
        """What the timings above replay on a batch of ``batch`` copies of ``img``, built once a size: ``parts``
        (backbone, then each head: compiled executors replay their CUDA graphs, eager ones are captured here if they
        can be) and all of them ``back_to_back``, ``upload`` and ``download``, and the device ``frames`` they read."""
        if batch in self._frame_runs:
            return self._frame_runs[batch]
        torch = self.torch
        with torch.inference_mode():
            host = torch.from_numpy(np.stack([img] * batch)).pin_memory()
            x = torch.empty_like(host, device=self.device)
            x.copy_(host)
            # a copy: the foundation's outputs live in its graphs' pool, where a replay of another batch size writes
            feats = {k: v.clone() for k, v in self.fm({"frame": x}).items()}
            parts: dict[str, Any] = {}
            outs = []
            for name, (fn, inputs) in {
                "foundation": (self.fm, {"frame": x}),
                **{name: (head, {k: feats[k] for k in keys}) for name, (head, keys) in self.heads.items()},
            }.items():
                parts[name] = (
                    (lambda fn=fn, inputs=inputs: fn(inputs)) if self.graphed[name] else _graphed(fn, inputs, torch)
                )
                if name != "foundation":
                    outs += [t for t in fn(inputs).values() if t.device.type == "cuda"]
            down = [torch.empty_like(t, device="cpu", pin_memory=True) for t in outs]
        self._frame_runs[batch] = {
            "frames": x,
            "parts": parts,
            "back_to_back": lambda: [run() for run in parts.values()],
            "upload": lambda: x.copy_(host, non_blocking=True),
            "download": lambda: [d.copy_(t, non_blocking=True) for d, t in zip(down, outs)],
        }
        return self._frame_runs[batch]


#: PyTorch hands out streams from a pool of this many per device and priority, round robin: more at once would share
STREAM_POOL = 32


def pipelined_ms(sets: list[InProcess], imgs: list[np.ndarray], batch: int, n: int = 100) -> float:
    """Device time (ms) a round takes in which every one of ``sets`` (the same models, built once each) runs a batch
    of ``batch`` frames (``imgs`` in turn, each copied ``batch`` times), rounds following one another as fast as the
    device takes them (CUDA only). In each set a batch's frames go up and its backbone runs on one stream, its
    features are copied into one of two buffers, then every head runs on a stream of its own and its outputs go down
    to page-locked host memory, beside the next batch's backbone; the sets run side by side. Compiled models replay
    their CUDA graphs; an eager one runs as it is (its launch gaps and any host synchronisation included).

    Unlike the models back to back, the models overlap as an engine's workers let them, with none of an engine's host
    work: one set on a batch of N frames is what an engine of N cameras would take at this schedule, N sets of one
    frame what N engines of one camera each would. A schedule, not a proof of the best one: the backbone runs at
    most one batch ahead of the heads (two buffers), and the sets are launched from one thread."""
    torch = sets[0].torch
    streams = len(sets) * (1 + len(sets[0].heads))
    if streams > STREAM_POOL:
        raise ValueError(
            f"{len(sets)} sets of {1 + len(sets[0].heads)} models need {streams} CUDA streams side by side; PyTorch's "
            f"pool has {STREAM_POOL} (more would share streams and run one after another): fewer frames"
        )
    lines = [_Pipeline(seq, imgs, batch) for seq in sets]
    main = torch.cuda.current_stream(sets[0].device)
    with torch.inference_mode():
        for line in lines:
            line.after(main)  # their set-up ran on this stream
        for i in range(10):  # warm-up
            for line in lines:
                line.issue(i)
        torch.cuda.synchronize(sets[0].device)
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record(main)
        for line in lines:
            line.after(main)
        for i in range(n):
            for line in lines:
                line.issue(i)
        for line in lines:
            line.before(main)
        end.record(main)
        end.synchronize()
    return start.elapsed_time(end) / n


class _Pipeline:
    """One set of models' batches, each issued on its streams to overlap the one before (``pipelined_ms``):
    ``issue(i)`` runs batch ``i`` on frame ``imgs[i % len(imgs)]``; ``downs`` holds each head's last outputs."""

    def __init__(self, seq: InProcess, imgs: list[np.ndarray], batch: int) -> None:
        from vpengine.backends.streams import lend

        torch = self.torch = seq.torch
        self.seq = seq
        with torch.inference_mode():
            self.hosts = [torch.from_numpy(np.stack([img] * batch)).pin_memory() for img in imgs]
            self.frames = torch.empty_like(self.hosts[0], device=seq.device)
            self.frames.copy_(self.hosts[0])
            feats = seq.fm({"frame": self.frames})
            self.bufs = [{k: v.clone() for k, v in feats.items()} for _ in range(2)]
            self.up = lend(self, seq.device)
            self.streams = {name: lend(self, seq.device) for name in seq.heads}
            self.downs = {
                name: [torch.empty_like(t, device="cpu", pin_memory=True) for t in head(self._inputs(keys, 0)).values()]
                for name, (head, keys) in seq.heads.items()
            }
        self.read = [[torch.cuda.Event() for _ in seq.heads] for _ in range(2)]  # its heads done with a buffer
        self.done = {name: torch.cuda.Event() for name in seq.heads}

    def _inputs(self, keys: list[str], j: int) -> dict[str, Any]:
        return {k: self.bufs[j][k] for k in keys}

    def issue(self, i: int) -> None:
        torch, j = self.torch, i % 2
        with torch.cuda.stream(self.up):
            self.frames.copy_(self.hosts[i % len(self.hosts)], non_blocking=True)
            feats = self.seq.fm({"frame": self.frames})
            for ev in self.read[j]:  # the heads of two batches ago have read this buffer
                self.up.wait_event(ev)
            for k, v in feats.items():
                self.bufs[j][k].copy_(v, non_blocking=True)
            ready = torch.cuda.Event()
            ready.record(self.up)
        for (name, (head, keys)), ev in zip(self.seq.heads.items(), self.read[j]):
            s = self.streams[name]
            with torch.cuda.stream(s):
                s.wait_event(ready)
                out = head(self._inputs(keys, j))
                ev.record(s)
                for d, t in zip(self.downs[name], out.values()):
                    d.copy_(t, non_blocking=True)
                self.done[name].record(s)

    def after(self, stream: Any) -> None:
        """Start no work before ``stream``'s."""
        self.up.wait_stream(stream)
        for s in self.streams.values():
            s.wait_stream(stream)

    def before(self, stream: Any) -> None:
        """``stream`` waits for every batch issued."""
        for ev in self.done.values():
            stream.wait_event(ev)
        stream.wait_stream(self.up)


def _graphed(fn: Any, inputs: dict[str, Any], torch: Any) -> Any:
    """A CUDA-graph replay of ``fn(inputs)`` if it captures (static shapes, no host syncs), else the plain call."""
    try:
        s = torch.cuda.Stream()
        s.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(s):
            for _ in range(3):
                fn(inputs)
        torch.cuda.current_stream().wait_stream(s)
        g = torch.cuda.CUDAGraph()
        with torch.cuda.graph(g):
            fn(inputs)
        return g.replay
    except Exception:
        torch.cuda.synchronize()
        return lambda: fn(inputs)


def engine_and_sequential(
    b: Bench, heads: list[dict[str, Any]], imgs: list[np.ndarray]
) -> tuple[dict[str, Any], dict[str, Any], dict[str, float]]:
    """The engine with ``heads`` (one frame in flight), then the same models run one after another in this process:
    their latencies, and each model's device time alone (empty off CUDA)."""
    with engines([b.config(heads)]) as (eng,):
        engine = lockstep(eng, imgs, b)
    seq = InProcess(b, heads)
    sequential = seq.latency(imgs, b.frames)
    device_ms = seq.device_times(imgs[0])
    del seq  # its models' memory goes before the next engine starts
    return engine, sequential, device_ms
