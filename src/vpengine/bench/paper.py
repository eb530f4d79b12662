"""The VPEngine paper's experiments, one protocol on any device, each comparison measured side by side in one run.

E1  shared backbone + N depth heads (engine) vs N independent full models vs one process running the heads one after
    another, N = 1..8 (paper: 2.3x over independent at 8 heads); plus the ideal ratio N(b+h)/(b+Nh) from the measured
    backbone time b and head time h.
E2  N detection heads: engine (parallel processes) vs one process running them one after another (paper: 3.3x at 8).
E3  CUDA MPS off vs on at N = 4 and 8 (paper: +39%, +77%).
E4  rate limits 5..30 Hz over 10 s of 30 Hz input: runs per head vs ideal (paper: +-1).
E5  a 30 Hz stream of 1080p frames with depth, segmentation and detection: per-head latency, frames lost, device
    memory over time (must stay flat).
E6  device memory and CPU per N, process and thread mode.
floor  the same models' summed device time (CUDA events, one process, CUDA graphs where possible), and the engine's
    overhead over it.

Latency is submit -> every head's result on the host, one frame in flight (lockstep), as in the paper; E5 measures it
under a continuous 30 Hz stream. Frames are synthetic 1080p scenes (content does not change the timing of dense
models). Models use random weights (the timing of a network does not depend on its weights).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from vpengine.bench.common import event_ms
from vpengine.config import RuntimeConfig

WAIT_SPIN_US: float = RuntimeConfig.model_fields["wait_spin_us"].default


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--experiments", default="E1,E2,E3,E4,E5,E6,floor", help="comma-separated subset")
    p.add_argument("--device", default="cuda")
    p.add_argument("--precision", default="fp16")
    p.add_argument("--heads", default="1,2,4,8", help="head counts for E1/E2/E6")
    p.add_argument("--frames", type=int, default=100, help="lockstep frames per measurement")
    p.add_argument("--e5-frames", type=int, default=10000, help="frames in the E5 stream (30 Hz)")
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--backbone", default="dinov2_vits14_dav2")
    p.add_argument("--depth-head", default="dav2_depth_s")
    p.add_argument("--seg-head", default="dinov2_linear_ade20k_s")
    p.add_argument("--det-head", default="frcnn_dinov2")
    p.add_argument(
        "--backend",
        default="eager",
        help="backend of every model (eager, compile, onnx); detection heads stay eager (NMS neither graphs nor exports)",
    )
    p.add_argument(
        "--mode",
        default="process",
        choices=["process", "thread"],
        help="engine mode of E1, E2, E4, E5 (independent models in E1 always run as separate processes)",
    )
    p.add_argument(
        "--mps",
        default="off",
        choices=["off", "required"],
        help="CUDA MPS for the engine and the independent models of E1 (E3 compares both; 'required' starts a "
        "private daemon for the run if none is reachable, and stops it at the end)",
    )
    p.add_argument(
        "--results",
        default="copy",
        choices=["copy", "borrow"],
        help="how the caller takes results: its own copies, or borrowed read-only views of the output mailboxes "
        "(Engine.wait(copy=False)); the sequential baseline copies with .cpu() either way",
    )
    p.add_argument(
        "--sync-spin-us",
        type=float,
        default=0.0,
        help="runtime.sync_spin_us of the engine's workers: 0 sleeps in the driver until device work is done; > 0 "
        "sleeps through the predicted part and polls the rest (Note [Device sync])",
    )
    p.add_argument(
        "--wait-spin-us",
        type=float,
        default=WAIT_SPIN_US,
        help="runtime.wait_spin_us: Engine.wait sleeps through the predicted part of a result handed off by event "
        "and polls for it within this window of its predicted end (default %(default)g), or sleeps in the driver "
        "until it is there (0) (Note [Result hand-off])",
    )
    p.add_argument(
        "--feature-handoff",
        default="event",
        choices=["event", "host"],
        help="runtime.feature_handoff: in thread mode on CUDA the foundation model publishes queued features with "
        "a device event the heads wait on (event), or waits for them on the host first (host; Note [Event hand-off])",
    )
    p.add_argument(
        "--result-handoff",
        default="event",
        choices=["event", "host"],
        help="runtime.result_handoff: in thread mode on CUDA each head publishes queued results with a device event "
        "Engine.wait sleeps on (event), or waits for them on the host first (host; Note [Result hand-off])",
    )
    p.add_argument(
        "--inline-launch",
        default="auto",
        choices=["auto", "always", "never"],
        help="runtime.inline_launch: in thread mode the thread that submits a frame queues the foundation model's "
        "work when it waits for one and runs from slot-bound CUDA graphs (auto), or its worker always does (never; "
        "Note [Inline launch])",
    )
    p.add_argument(
        "--no-slot-bound",
        action="store_true",
        help="compiled models copy each input and output tensor in the worker instead of running from graphs bound "
        "to the mailbox slots (backend_options.slot_bound: false; for comparisons)",
    )
    p.add_argument(
        "--floor-heads", default="depth,seg,det", help="heads of the floor experiment (depth, seg, det)"
    )
    p.add_argument(
        "--stream-priorities",
        default="",
        help="stream_priority of models by kind, e.g. depth=-1 (foundation, depth, seg, det; 0 normal, negative "
        "higher): the heads of every experiment get the priority of their kind",
    )
    p.add_argument(
        "--seg-upsample",
        default="auto",
        choices=["auto", "fused", "torch"],
        help="options.upsample of the linear segmentation head: its fused Triton kernel where it can run (auto), "
        "or PyTorch's interpolate and argmax (torch; for comparisons; Note [Fused upsample + argmax])",
    )
    p.add_argument("--tiny", action="store_true", help="tiny models on small frames (a CPU smoke run)")
    p.add_argument("--tag", default="", help="suffix of the results file name")


@dataclass
class Setup:
    device: str = "cuda"
    precision: str = "fp16"
    height: int = 1080
    width: int = 1920
    backbone: str = "dinov2_vits14_dav2"
    depth: str = "dav2_depth_s"
    seg: str = "dinov2_linear_ade20k_s"
    det: str = "frcnn_dinov2"
    det_options: dict[str, Any] = field(default_factory=lambda: {"num_classes": 80})
    backbone_options: dict[str, Any] = field(default_factory=dict)
    backend: str = "eager"
    frames: int = 100
    tiny: bool = False
    mode: str = "process"
    mps: str = "off"
    mps_pipe_directory: str | None = None
    results: str = "copy"
    sync_spin_us: float = 0.0
    wait_spin_us: float = WAIT_SPIN_US
    slot_bound: bool = True
    feature_handoff: str = "event"
    result_handoff: str = "event"
    inline_launch: str = "auto"
    stream_priorities: dict[str, int] = field(default_factory=dict)
    #: options.upsample of a linear segmentation head; "auto" leaves the option out (the tiny seg head has none)
    seg_upsample: str = "auto"

    @property
    def copy(self) -> bool:
        return self.results == "copy"

    @property
    def engine_label(self) -> str:
        spin = f", sync spin {self.sync_spin_us:g} us" if self.sync_spin_us else ""
        # the wait spin is CUDA's alone (results handed off by event)
        spin += (
            f", wait spin {self.wait_spin_us:g} us"
            if self.wait_spin_us and self.device.startswith("cuda")
            else ""
        )
        handoff = ", host hand-off" if self.feature_handoff == "host" else ""
        handoff += ", results handed off on the host" if self.result_handoff == "host" else ""
        launch = ", worker launch" if self.inline_launch == "never" else ""
        upsample = f", seg upsample {self.seg_upsample}" if self.seg_upsample != "auto" else ""
        return f"{self.mode} mode, MPS {self.mps}, results {self.results}{spin}{handoff}{launch}{upsample}"

    @classmethod
    def from_args(cls, a: argparse.Namespace) -> Setup:
        if a.tiny:
            return cls(
                device=a.device,
                precision="fp32",
                height=120,
                width=160,
                backbone="tiny_vit",
                depth="tiny_depth",
                seg="tiny_seg",
                det="tiny_det",
                det_options={},
                frames=a.frames,
                backbone_options={},
                backend=a.backend,
                tiny=True,
                mode=a.mode,
                mps=a.mps,
                results=a.results,
                sync_spin_us=a.sync_spin_us,
                wait_spin_us=a.wait_spin_us,
                slot_bound=not a.no_slot_bound,
                feature_handoff=a.feature_handoff,
                result_handoff=a.result_handoff,
                inline_launch=a.inline_launch,
                stream_priorities=parse_priorities(a.stream_priorities),
            )
        return cls(
            device=a.device,
            precision=a.precision,
            height=a.height,
            width=a.width,
            backbone=a.backbone,
            depth=a.depth_head,
            seg=a.seg_head,
            det=a.det_head,
            backend=a.backend,
            frames=a.frames,
            mode=a.mode,
            mps=a.mps,
            results=a.results,
            sync_spin_us=a.sync_spin_us,
            wait_spin_us=a.wait_spin_us,
            slot_bound=not a.no_slot_bound,
            feature_handoff=a.feature_handoff,
            result_handoff=a.result_handoff,
            inline_launch=a.inline_launch,
            stream_priorities=parse_priorities(a.stream_priorities),
            seg_upsample=a.seg_upsample,
        )

    def head(self, kind: str, name: str, **extra: Any) -> dict[str, Any]:
        model = {"depth": self.depth, "seg": self.seg, "det": self.det}[kind]
        opts = self.det_options if kind == "det" else {}
        if kind == "seg" and self.seg_upsample != "auto":
            opts = {"upsample": self.seg_upsample}
        # Faster R-CNN's NMS has data-dependent shapes: it neither compiles into a CUDA graph nor exports; eager
        backend = "eager" if kind == "det" and self.backend != "eager" else self.backend
        return {
            "name": name,
            "model": model,
            "options": opts,
            "backend": backend,
            **self._backend_options(backend),
            **self._priority(kind),
            **extra,
        }

    def _priority(self, kind: str) -> dict[str, Any]:
        p = self.stream_priorities.get(kind)
        return {} if p is None else {"stream_priority": p}

    def _backend_options(self, backend: str) -> dict[str, Any]:
        if backend == "compile" and not self.slot_bound:
            return {"backend_options": {"slot_bound": False}}
        return {}

    def config(self, heads: list[dict[str, Any]], mode: str | None = None, **top: Any) -> Any:
        from vpengine.config import load_config

        raw = {
            "name": "bench",
            "mode": mode or self.mode,
            "device": self.device,
            "precision": self.precision,
            "mps": self.mps,
            **({"mps_pipe_directory": self.mps_pipe_directory} if self.mps_pipe_directory else {}),
            "input": {"height": self.height, "width": self.width},
            "foundation_model": {
                "model": self.backbone,
                "options": self.backbone_options,
                "backend": self.backend,
                **self._backend_options(self.backend),
                **self._priority("foundation"),
            },
            "heads": heads,
            "weights": {"random_weights": True},
            "runtime": {
                "sync_spin_us": self.sync_spin_us,
                "wait_spin_us": self.wait_spin_us,
                "feature_handoff": self.feature_handoff,
                "result_handoff": self.result_handoff,
                "inline_launch": self.inline_launch,
            },
            "logging": {"level": "WARNING"},
            **top,
        }
        if self.tiny:
            raw["foundation_model"]["preprocess"] = {"size": 112}
        return load_config(raw)


# ----------------------------------------------------------------------------------------------- helpers
def parse_priorities(text: str) -> dict[str, int]:
    """``depth=-1,seg=0`` -> {"depth": -1, "seg": 0} (``--stream-priorities``)."""
    out: dict[str, int] = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        kind, sep, value = item.partition("=")
        kind = kind.strip()
        if not sep or kind not in ("foundation", "depth", "seg", "det"):
            raise ValueError(
                f"--stream-priorities item {item!r}: expected KIND=PRIORITY with KIND one of foundation, depth, "
                "seg, det"
            )
        try:
            out[kind] = int(value)
        except ValueError:
            raise ValueError(
                f"--stream-priorities item {item!r}: priority {value.strip()!r} is not an integer"
            ) from None
    return out


def frames(setup: Setup, n: int = 8) -> list[np.ndarray]:
    from vpengine.io.sources import SyntheticSource

    src = SyntheticSource(setup.width, setup.height, 30.0, n)
    return [src.render(i * 3) for i in range(n)]


def pct(values: list[float] | np.ndarray) -> dict[str, float]:
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


def lockstep(
    engine: Any, imgs: list[np.ndarray], setup: Setup, warmup: int = 10, slot: bool = False
) -> dict[str, float]:
    """submit -> all heads' results on the host, one frame in flight, ``setup.frames`` times (results copied or
    borrowed as ``setup.results`` says).

    ``slot``: the frame is written in place into the input mailbox (``Engine.frame_slot``), as a camera's decode
    would write it, and timed from the end of that write: the engine's latency without ``submit``'s copy.
    """

    def step(i: int) -> float | None:
        if not slot:
            engine.wait(engine.submit(imgs[i % len(imgs)]), timeout=120, copy=setup.copy)
            return None
        with engine.frame_slot() as s:
            np.copyto(s.array, imgs[i % len(imgs)])
            t0 = time.perf_counter()
        engine.wait(s.frame_id, timeout=120, copy=setup.copy)
        return t0

    return timed(step, setup.frames, warmup)


def _sync(device: Any) -> None:
    import torch

    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


class InProcess:
    """The same recipes built in this process (no engine): the sequential baseline and the device-time floor."""

    def __init__(self, setup: Setup, heads: list[dict[str, Any]]) -> None:
        import torch

        from vpengine.backends import make_executor
        from vpengine.models.build import build_model
        from vpengine.runtime.plan import make_plan

        self.cfg = cfg = setup.config(heads, mode="thread")
        self.device = torch.device(setup.device)
        plan = make_plan(cfg)

        def executor(model: Any, mcfg: Any, name: str) -> Any:  # exactly as a worker builds it
            return make_executor(
                model,
                mcfg.backend,
                self.device,
                name,
                options=mcfg.backend_options,
                precision=mcfg.precision or cfg.precision,
                cache_dir=cfg.weights.cache_dir,
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
        self._frame_runs: dict[str, Any] | None = None

    def run(self, img: np.ndarray) -> dict[str, Any]:
        """Backbone once, then every head one after another, outputs copied to the host."""
        torch = self.torch
        with torch.inference_mode():
            x = torch.from_numpy(img).to(self.device, non_blocking=True)
            feats = self.fm({"frame": x})
            outs = {}
            for name, (head, keys) in self.heads.items():
                out = head({k: feats[k] for k in keys})
                outs[name] = {k: v.cpu() for k, v in out.items()}
        return outs

    def latency(self, imgs: list[np.ndarray], n: int, warmup: int = 10) -> dict[str, float]:
        return timed(lambda i: self.run(imgs[i % len(imgs)]), n, warmup)

    def device_times(self, img: np.ndarray, n: int = 50) -> dict[str, float]:
        """Median device time (ms) of the backbone and of each head, each timed alone, with CUDA graphs where they
        capture (empty off CUDA)."""
        if self.device.type != "cuda":
            return {}
        parts = self._frame(img)["parts"]
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
        runs = list(f["parts"].values())

        def compute() -> None:
            for run in runs:
                run()

        def whole() -> None:
            f["upload"]()
            compute()
            f["download"]()

        with self.torch.inference_mode():
            return {
                "compute": event_ms(compute, n),
                "with_transfers": event_ms(whole, n),
            }

    def _frame(self, img: np.ndarray) -> dict[str, Any]:
        """What the timings above replay, built once: ``parts`` (backbone, then each head: compiled executors replay
        their CUDA graphs, eager ones are captured here if they can be), ``upload`` and ``download``."""
        if self._frame_runs is not None:
            return self._frame_runs
        torch = self.torch
        with torch.inference_mode():
            host = torch.from_numpy(img).pin_memory()
            x = torch.empty_like(host, device=self.device)
            x.copy_(host)
            feats = self.fm({"frame": x})
            parts: dict[str, Any] = {}
            outs = []
            for name, (fn, inputs) in {
                "foundation": (self.fm, {"frame": x}),
                **{name: (head, {k: feats[k] for k in keys}) for name, (head, keys) in self.heads.items()},
            }.items():
                parts[name] = (
                    (lambda fn=fn, inputs=inputs: fn(inputs))
                    if self.graphed[name]
                    else _graphed(fn, inputs, torch)
                )
                if name != "foundation":
                    outs += [t for t in fn(inputs).values() if t.device.type == "cuda"]
            down = [torch.empty_like(t, device="cpu", pin_memory=True) for t in outs]
        self._frame_runs = {
            "parts": parts,
            "upload": lambda: x.copy_(host, non_blocking=True),
            "download": lambda: [d.copy_(t, non_blocking=True) for d, t in zip(down, outs)],
        }
        return self._frame_runs


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


def independent_latency(
    es: list[Any], imgs: list[np.ndarray], setup: Setup, warmup: int = 10
) -> dict[str, float]:
    """N independent full pipelines (each its own backbone): a frame goes to all, latency = the slowest."""

    def one(i: int) -> None:
        fids = [e.submit(imgs[i % len(imgs)]) for e in es]
        for e, fid in zip(es, fids):
            e.wait(fid, timeout=120, copy=setup.copy)

    return timed(one, setup.frames, warmup)


def log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", flush=True)


# ------------------------------------------------------------------------------------------- experiments
def engine_and_sequential(
    setup: Setup, heads: list[dict[str, Any]], imgs: list[np.ndarray]
) -> tuple[dict[str, Any], dict[str, Any], dict[str, float]]:
    """The engine with ``heads`` (one frame in flight), then the same models run one after another in this process:
    their latencies, and each model's device time alone (empty on the CPU)."""
    with engines([setup.config(heads)]) as (eng,):
        engine = lockstep(eng, imgs, setup)
    seq = InProcess(setup, heads)
    sequential = seq.latency(imgs, setup.frames)
    device_ms = seq.device_times(imgs[0])
    del seq  # its models' memory goes before the next engine starts
    return engine, sequential, device_ms


def e1(setup: Setup, ns: list[int], imgs: list[np.ndarray]) -> dict[str, Any]:
    rows = []
    for n in ns:
        shared, sequential, dt = engine_and_sequential(
            setup, [setup.head("depth", f"depth{i}") for i in range(n)], imgs
        )
        with engines([setup.config([setup.head("depth", "depth")], mode="process") for _ in range(n)]) as es:
            indep = independent_latency(es, imgs, setup)
        row = {
            "heads": n,
            "engine": shared,
            "independent": indep,
            "sequential": sequential,
            "device_ms": dt,
            "speedup_vs_independent": indep["mean"] / shared["mean"],
            "speedup_vs_sequential": sequential["mean"] / shared["mean"],
        }
        if dt:
            b, h = dt["foundation"], dt["depth0"]
            row["ideal_vs_independent"] = n * (b + h) / (b + n * h)
        rows.append(row)
        log(
            f"E1 N={n}: engine ({setup.engine_label}) {shared['mean']:.1f} ms, independent {indep['mean']:.1f} ms "
            f"({row['speedup_vs_independent']:.2f}x), sequential {sequential['mean']:.1f} ms "
            f"({row['speedup_vs_sequential']:.2f}x)"
            + (f", ideal {row['ideal_vs_independent']:.2f}x" if dt else "")
        )
    return {"rows": rows}


def e2(setup: Setup, ns: list[int], imgs: list[np.ndarray]) -> dict[str, Any]:
    rows = []
    for n in ns:
        parallel, sequential, dt = engine_and_sequential(
            setup, [setup.head("det", f"det{i}") for i in range(n)], imgs
        )
        row = {
            "heads": n,
            "engine": parallel,
            "sequential": sequential,
            "device_ms": dt,
            "speedup_vs_sequential": sequential["mean"] / parallel["mean"],
        }
        rows.append(row)
        log(
            f"E2 N={n}: engine ({setup.engine_label}) {parallel['mean']:.1f} ms, sequential {sequential['mean']:.1f} ms "
            f"({row['speedup_vs_sequential']:.2f}x)"
        )
    return {"rows": rows}


def e3(setup: Setup, imgs: list[np.ndarray], ns: tuple[int, ...] = (4, 8)) -> dict[str, Any]:
    rows = []
    with _mps_daemon() as daemon:
        for kind in ("det", "depth"):
            for n in ns:
                heads = [setup.head(kind, f"{kind}{i}") for i in range(n)]
                res = {}
                for setting in ("off", "required"):
                    cfg = setup.config(heads, mps=setting, mps_pipe_directory=daemon)
                    with engines([cfg]) as (eng,):
                        res[setting] = lockstep(eng, imgs, setup)
                        res[setting]["workers_on_mps"] = len(eng.stats()["engine"]["mps"]["workers_on_mps"])
                gain = res["off"]["mean"] / res["required"]["mean"] - 1
                rows.append(
                    {
                        "head": kind,
                        "heads": n,
                        "mps_off": res["off"],
                        "mps_on": res["required"],
                        "throughput_gain": gain,
                    }
                )
                log(
                    f"E3 {kind} N={n}: MPS off {res['off']['hz']:.1f} Hz, on {res['required']['hz']:.1f} Hz "
                    f"({gain:+.0%}, {res['required']['workers_on_mps']} workers on MPS)"
                )
    return {"rows": rows, "mps_pipe_directory": daemon}


def e4(setup: Setup, imgs: list[np.ndarray], seconds: float = 10.0) -> dict[str, Any]:
    rates = [5, 10, 15, 20, 25, 30]
    heads = [setup.head("depth", f"r{r}", rate_hz=r) for r in rates]
    with engines([setup.config(heads)]) as (eng,):
        for i in range(5):
            eng.wait(eng.submit(imgs[i % len(imgs)]), timeout=120)
        before = {k: v["runs"] for k, v in eng.stats()["models"].items()}
        time.sleep(1.0)  # idle gap: the schedule must restart cleanly
        t0 = time.monotonic()
        n = 0
        while True:
            t = t0 + n / 30.0
            if t - t0 >= seconds:
                break
            d = t - time.monotonic()
            if d > 0:
                time.sleep(d)
            eng.submit(imgs[n % len(imgs)])
            n += 1
        time.sleep(0.5)
        st = eng.stats()["models"]
    rows = []
    fm_runs = st["foundation"]["runs"] - before["foundation"]
    for r in rates:
        runs = st[f"r{r}"]["runs"] - before[f"r{r}"]
        ideal = min(r * seconds, fm_runs)  # a head cannot run on frames the backbone skipped
        rows.append(
            {
                "rate_hz": r,
                "runs": runs,
                "ideal": ideal,
                "error": runs - ideal,
                "skipped": st[f"r{r}"]["skipped"],
            }
        )
    log(
        f"E4 (backbone ran {fm_runs} of {n} frames) "
        + ", ".join(f"{x['rate_hz']} Hz: {x['runs']} ({x['error']:+.0f})" for x in rows)
    )
    return {"rows": rows, "input_frames": n, "foundation_runs": fm_runs, "seconds": seconds}


def e5(setup: Setup, imgs: list[np.ndarray], n_frames: int) -> dict[str, Any]:
    from vpengine.runtime.gpu import device_memory_used, process_memory

    heads = [setup.head("depth", "depth"), setup.head("seg", "seg"), setup.head("det", "det")]
    lat: dict[str, list[float]] = {"depth": [], "seg": [], "det": []}
    per_frame: dict[int, dict[str, float]] = {}
    memory: list[dict[str, Any]] = []
    with engines([setup.config(heads)]) as (eng,):
        for i in range(30):
            eng.wait(eng.submit(imgs[i % len(imgs)]), timeout=120)
        eng.results()
        pids = [m["pid"] for m in eng.stats()["models"].values()]
        index = 0 if setup.device == "cuda" else None
        t0 = time.monotonic()
        next_mem = t0
        first_id = None
        for k in range(n_frames):
            t = t0 + k / 30.0
            while (now := time.monotonic()) < t:
                for r in eng.results(timeout=t - now, copy=setup.copy):
                    lat[r.head].append(r.latency)
                    per_frame.setdefault(r.frame_id, {})[r.head] = r.latency
            fid = eng.submit(imgs[k % len(imgs)])
            first_id = fid if first_id is None else first_id
            if index is not None and time.monotonic() >= next_mem:
                per = process_memory(index)
                memory.append(
                    {
                        "t": time.monotonic() - t0,
                        "frame": k,
                        "device_used": device_memory_used(index),
                        "workers": [per.get(p) for p in pids],
                    }
                )
                next_mem += 1.0
            if k and k % 1000 == 0:
                log(f"E5 {k}/{n_frames} frames")
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            rs = eng.results(timeout=0.5, copy=setup.copy)
            for r in rs:
                lat[r.head].append(r.latency)
                per_frame.setdefault(r.frame_id, {})[r.head] = r.latency
            if not rs:
                break
        st = eng.stats()
    complete = [max(v.values()) for v in per_frame.values() if len(v) == 3]
    lost = {h: n_frames - len(v) for h, v in lat.items()}
    res_missed = {h: st["results"][h]["missed"] for h in lat}
    mem_used = [m["device_used"] for m in memory if m["device_used"] is not None]
    out = {
        "frames": n_frames,
        "per_head_latency_ms": {h: pct(v) for h, v in lat.items()},
        "all_three_latency_ms": pct(complete),
        "frames_lost": lost,
        "loss_pct": {h: 100.0 * v / n_frames for h, v in lost.items()},
        "results_missed": res_missed,
        "skipped": {h: st["models"][h]["skipped"] for h in lat}
        | {"foundation": st["models"]["foundation"]["skipped"]},
        "memory": memory,
        "memory_flat": bool(mem_used)
        and (max(mem_used[len(mem_used) // 10 :]) - min(mem_used[len(mem_used) // 10 :])) == 0,
    }
    a3 = out["all_three_latency_ms"]
    log(
        f"E5 {n_frames} frames at 30 Hz: all three heads p50 {a3['p50']:.1f} ms p99 {a3['p99']:.1f} ms; "
        f"lost {out['loss_pct']}; memory flat: {out['memory_flat']}"
    )
    return out


def e6(setup: Setup, ns: list[int]) -> dict[str, Any]:
    from vpengine.bench.resources import isolated as resources

    rows = []
    base = setup.config([setup.head("depth", "depth")])
    import tempfile

    with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as f:
        f.write(json.dumps(base.model_dump(mode="json")))
        path = f.name
    for mode in ("process", "thread"):
        for n in ns:
            r = resources(path, n, mode, setup.height, setup.width, 5.0, [], cpu=True)
            rows.append(r)
            log(
                f"E6 {mode} N={n}: device +{r['device_mem_mb']:.0f} MB, CPU idle {r['cpu_idle_pct']:.1f}%, "
                f"30 Hz {r['cpu_30hz_pct']:.0f}%"
            )
    return {"rows": rows}


def _floor_kinds(kinds: tuple[str, ...]) -> tuple[str, ...]:
    bad = sorted(set(kinds) - {"depth", "seg", "det"})
    if bad or not kinds:
        raise ValueError(f"floor heads {list(kinds)}: accepted are depth, seg, det (at least one)")
    return kinds


def floor(
    setup: Setup, imgs: list[np.ndarray], kinds: tuple[str, ...] = ("depth", "seg", "det")
) -> dict[str, Any]:
    """Engine (thread and process mode, same backend) vs the device-time floor of the same models in one process."""
    heads = [setup.head(k, k) for k in _floor_kinds(kinds)]
    seq = InProcess(setup, heads)
    dt = seq.device_times(imgs[0])
    xfer = seq.transfer_times(imgs[0])
    chained = seq.chained_times(imgs[0])
    del seq
    out: dict[str, Any] = {"device_ms": dt, "transfer_ms": xfer, "chained_ms": chained}
    if dt:
        out["floor_sum_ms"] = sum(dt.values())
        # the frame has to get onto the device and the results off it: the floor with those copies
        out["floor_with_transfers_ms"] = out["floor_sum_ms"] + sum(xfer.values())
    for mode in ("thread", "process"):
        with engines([setup.config(heads, mode=mode)]) as (eng,):
            out[mode] = lockstep(eng, imgs, setup)
            # the same engine with frames written in place (Engine.frame_slot): no copy at submit
            out[f"{mode}_frame_slot"] = lockstep(eng, imgs, setup, slot=True)
        if dt:
            for key in (mode, f"{mode}_frame_slot"):
                out[f"{key}_overhead_vs_floor"] = out[key]["mean"] / out["floor_sum_ms"] - 1
                out[f"{key}_overhead_vs_floor_with_transfers"] = (
                    out[key]["mean"] / out["floor_with_transfers_ms"] - 1
                )
                out[f"{key}_overhead_vs_chained"] = out[key]["mean"] / chained["compute"] - 1
    log(
        f"floor: device time {dt} -> sum {out.get('floor_sum_ms', float('nan')):.1f} ms, with transfers {xfer} "
        f"{out.get('floor_with_transfers_ms', float('nan')):.1f} ms, chained { ({k: round(v, 2) for k, v in chained.items()}) }; engine thread "
        f"{out['thread']['mean']:.1f} ms ({out['thread_frame_slot']['mean']:.1f} ms from a frame slot), process "
        f"{out['process']['mean']:.1f} ms ({out['process_frame_slot']['mean']:.1f} ms)"
    )
    return out


# ------------------------------------------------------------------------------------------------ figures
def figures(res: dict[str, Any], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [k for k in ("E1", "E2", "E3", "E4", "E5", "E6") if k in res]
    if not panels:
        return
    cols = min(3, len(panels))
    rows = math.ceil(len(panels) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.8 * rows), dpi=110, squeeze=False)
    for ax in axes.flat[len(panels) :]:
        ax.axis("off")
    for ax, key in zip(axes.flat, panels):
        r = res[key]
        if key in ("E1", "E2"):
            ns = [x["heads"] for x in r["rows"]]
            series = ["engine", "sequential"] + (["independent"] if key == "E1" else [])
            st = res.get("setup", {})
            engine_label = (
                f"engine ({st.get('mode', 'process')} mode{', MPS' if st.get('mps') == 'required' else ''})"
            )
            for s in series:
                ax.plot(
                    ns,
                    [x[s]["hz"] for x in r["rows"]],
                    marker="o",
                    label=engine_label if s == "engine" else s,
                )
            ax.set_xlabel("heads")
            ax.set_ylabel("frames/s (one in flight)")
            ax.set_title(f"{key}: {'depth' if key == 'E1' else 'detection'} heads")
            ax.legend()
        elif key == "E3":
            labels = [f"{x['head']} x{x['heads']}" for x in r["rows"]]
            x = np.arange(len(labels))
            ax.bar(x - 0.2, [y["mps_off"]["hz"] for y in r["rows"]], 0.4, label="MPS off")
            ax.bar(x + 0.2, [y["mps_on"]["hz"] for y in r["rows"]], 0.4, label="MPS on")
            ax.set_xticks(x, labels)
            ax.set_ylabel("frames/s")
            ax.set_title("E3: CUDA MPS")
            ax.legend()
        elif key == "E4":
            rates = [x["rate_hz"] for x in r["rows"]]
            ax.plot(rates, [x["ideal"] for x in r["rows"]], "k--", label="ideal R x 10 s")
            ax.plot(rates, [x["runs"] for x in r["rows"]], "o", label="measured")
            ax.set_xlabel("rate limit (Hz)")
            ax.set_ylabel("runs in 10 s")
            ax.set_title("E4: rate limits")
            ax.legend()
        elif key == "E5":
            mem = r["memory"]
            if mem and mem[0]["device_used"] is not None:
                base = mem[0]["device_used"]
                ax.plot([m["t"] for m in mem], [(m["device_used"] - base) / 2**20 for m in mem])
                ax.set_xlabel("seconds")
                ax.set_ylabel("device memory change (MiB)")
                ax.ticklabel_format(useOffset=False)
            lat = r["per_head_latency_ms"]
            ax.set_title(
                "E5: 30 Hz stream; p50 " + ", ".join(f"{h} {v['p50']:.1f}" for h, v in lat.items()) + " ms",
                fontsize=9,
            )
        elif key == "E6":
            for mode in ("process", "thread"):
                pts = [(x["heads"], x["device_mem_mb"]) for x in r["rows"] if x["mode"] == mode]
                if pts:
                    ax.plot(*zip(*pts), marker="o", label=mode)
            ax.set_xlabel("heads")
            ax.set_ylabel("device memory (MB)")
            ax.set_title("E6: memory per head count")
            ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(args: argparse.Namespace) -> int:
    setup = Setup.from_args(args)
    ns = [int(x) for x in args.heads.split(",")]
    want = [x.strip() for x in args.experiments.split(",") if x.strip()]
    floor_kinds = _floor_kinds(tuple(k.strip() for k in args.floor_heads.split(",") if k.strip()))
    imgs = frames(setup)
    with contextlib.ExitStack() as stack:
        if setup.mps == "required":
            setup.mps_pipe_directory = stack.enter_context(_mps_daemon())
        res, path = _run(setup, want, ns, imgs, floor_kinds, args)
    figures(res, str(path.with_suffix(".png")))
    log(f"-> {path} and {path.with_suffix('.png')}")
    return 0


@contextlib.contextmanager
def _mps_daemon() -> Iterator[str]:
    """The pipe directory of a reachable MPS daemon, or of a private one started here and stopped on exit."""
    from vpengine.runtime import mps

    daemon = mps.find_daemon()
    started = None
    if daemon is None:
        started = mps.start()
        daemon = started["pipe_directory"]
    log(f"MPS daemon at {daemon} ({'started for this run' if started else 'already running'})")
    try:
        yield daemon
    finally:
        if started and started.get("started"):
            mps.stop(daemon)


def _run(
    setup: Setup,
    want: list[str],
    ns: list[int],
    imgs: list[np.ndarray],
    floor_kinds: tuple[str, ...],
    args: argparse.Namespace,
) -> tuple[dict[str, Any], Any]:
    from vpengine.bench.common import machine_info, write_results

    res: dict[str, Any] = {"setup": asdict(setup)}
    log(f"machine: {machine_info()}")
    path = None
    for key in want:
        t = time.monotonic()
        if key == "E1":
            res[key] = e1(setup, ns, imgs)
        elif key == "E2":
            res[key] = e2(setup, ns, imgs)
        elif key == "E3":
            res[key] = e3(setup, imgs)
        elif key == "E4":
            res[key] = e4(setup, imgs)
        elif key == "E5":
            res[key] = e5(setup, imgs, args.e5_frames)
        elif key == "E6":
            res[key] = e6(setup, ns)
        elif key == "floor":
            res[key] = floor(setup, imgs, floor_kinds)
        else:
            raise ValueError(f"unknown experiment {key!r}; accepted: E1..E6, floor")
        res[key]["seconds"] = time.monotonic() - t
        name = f"paper_{setup.device}{('_' + args.tag) if args.tag else ''}"
        path = write_results(args.out, name, res)  # after every experiment: a crash keeps what was measured
    if path is None:
        raise ValueError("no experiment given (--experiments is empty)")
    return res, path
