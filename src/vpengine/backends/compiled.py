"""``torch.compile``: inductor kernels, replayed as CUDA graphs on CUDA devices, one per batch size.

Note [CUDA graphs]
~~~~~~~~~~~~~~~~~
On a CUDA device the compiled model is captured at warm-up into one ``torch.cuda.CUDAGraph`` per batch size
``B = 1 .. max_batch`` (Note [Executor contract] in base.py) over static buffers: a call of ``B`` frames copies the
inputs into static input tensors, replays the graph of ``B`` and returns that graph's static output tensors, which
the worker copies into its output slots. The static inputs are one buffer per key for ``max_batch`` frames; the
graph of ``B`` reads its first ``B`` frames (a view at offset 0), so a bigger ``max_batch`` costs no extra input
copies. We capture explicitly instead of using ``mode="reduce-overhead"`` (inductor's CUDA graph trees) because a
robot process runs for days and must behave the same on frame 10 and frame 10 million:

* Failure is loud and early. Graph trees skip CUDA graphs with a log line when they meet something they cannot
  capture (CPU tensors, input mutation, a host sync) and the steady state then allocates per frame; an explicit
  capture either succeeds before READY or fails the worker's start with the reason.
* Nothing is re-recorded. Graph trees re-record on new static-input addresses or shapes, on a new "generation", or
  when outputs of an earlier replay are still alive; each re-recording costs a stall and pool memory. Our graphs
  are recorded once, every batch size before READY, into one private memory pool that they share (a replay of one
  may overwrite what another left in the pool, which is harmless: a call's outputs are valid only until the next
  call, and calls never overlap); a replay allocates nothing, so ``memory_allocated`` stays flat (Invariant:
  constant memory). The largest batch is captured first: the pool grows to its peak once, and each smaller graph
  takes its outputs and intermediates out of the room the larger one's intermediates freed, so the pool holds about
  what the largest batch needs, not the sum over all sizes. (Captured smallest first, each graph's outputs, alive
  for good, split the pool where the next and larger one's intermediates had to go: about half as much again,
  docs/benchmarks.md.) So a replay of the largest batch overwrites the outputs of every smaller one, which the
  contract allows.
* No thread affinity. Graph trees keep per-thread state and assert when a graph recorded in one thread is replayed
  from another (pytorch/pytorch#123177); thread mode runs every model in its own thread. A CUDAGraph object can be
  replayed from any thread.
* Plain stream semantics. ``replay()`` enqueues on the caller's current stream -- the worker's own stream
  (``DeviceContext.active``) -- after the copies into the static inputs and before the worker's copies out of the
  static outputs, so stream order alone makes it correct. Capture happens on a private side stream nobody else uses,
  after ``warmup_iters`` runs of every batch size on that stream (lazy cuBLAS/cuDNN set-up must not happen inside a
  capture).
* Captures use ``capture_error_mode="thread_local"``: other workers' threads (thread mode) may keep calling the CUDA
  API (allocations, event waits) while one captures; captures within a process take a lock so pools never interleave.

The price is one device-to-device copy of the inputs per frame, small next to a backbone (features of a ViT-S at
518x518 are ~8 MB). Inductor's own CUDA graphs are never enabled (``max-autotune`` maps to
``max-autotune-no-cudagraphs``), so there are never two layers of graphs.

The CPU path compiles the same way (inductor generates C++, built with the system compiler), and also feeds the
compiled code from the static input buffers: each batch size always sees the same tensors, so dynamo's guards
(dtype, shape, strides, whether a tensor is an inference tensor) cannot fail and recompile in the steady state, and
inductor's alignment assumptions hold (per-key views carved out of one mailbox allocation need not be 16-byte
aligned).

Note [One compile for every batch]
~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~
A model is compiled twice, not once per batch size: for a batch of one, with every shape fixed as the single-frame
code always was, and once for any batch from 2 to ``max_batch``, whose batch dimension is symbolic (before they
first run, the static views of 2 or more frames are marked dynamic in that dimension, and every view static in all
its others, so no other dimension turns symbolic however other models of the process were compiled); the graphs are
still captured one per size. With ``max_batch`` 2 or less every shape stays fixed, as before. A first start of eight
cameras compiled each of its four models eight times: minutes on an H200 in thread mode, where builds take turns.
What that saves at start, and what it costs or saves per call, against a compile per size, is what
``benchmarks/compile_batches.py`` measures, outputs compared. A model whose code fixes its batch to a number (a
Python list as long as the batch, ``int(x.shape[0])`` in arithmetic) is compiled per size instead: the mark is a hint
(``maybe_mark_dynamic``); one that fails to compile with a symbolic batch is compiled per size, with a warning saying
why. The built-in models are held to two compiled graphs (three for the detector, whose anchors fill a cache on the
first call), and their batches to the eager model's outputs, by a test.

What inductor and Triton write to disk goes to a folder keyed on the release (Note [Compile cache key] in
compile_cache.py), so a start never reads what another release compiled.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import TimeoutError as FuturesTimeout  # not the builtin before Python 3.11
from typing import Any

import torch

from vpengine.backends.base import Executor, PrecisionRunner, cast_model_, tensor_bytes
from vpengine.backends.compile_cache import use_compile_cache
from vpengine.backends.options import BackendError, CompileOptions
from vpengine.backends.streams import lend
from vpengine.models.base import Model

log = logging.getLogger("vpengine.backends")

# One CUDA graph capture at a time per process (thread mode warms several models up concurrently).
_CAPTURE_LOCK = threading.Lock()


# Note [Compile workers]
# ~~~~~~~~~~~~~~~~~~~~~~
# Inductor compiles Triton kernels in a pool of worker processes, but only once the pool has answered a first
# job; until then (and without a pool) it compiles them in the calling thread, where Triton's LLVM passes hold the
# interpreter lock for tens of milliseconds a kernel (56-73 ms seen on an H200, for kernels of a compiled detection
# head loaded from a warm FX-graph cache). In thread mode every serving worker stops meanwhile (Note [Building
# beside serving threads] in runtime/threads.py). So a compiled model built beside serving threads first waits for
# the pool (``compile_workers_ready``): its kernels then compile, or load from Triton's cache, in the workers. At an
# add with a warm compile cache the pool was not yet ready (its first job had not answered 30 s after the engine's
# start). Only there: a start has nothing serving to stall, and waiting would only make it later.
COMPILE_WORKERS_WAIT_S = 60.0


def compile_workers_ready(
    timeout_s: float = COMPILE_WORKERS_WAIT_S, cancelled: Callable[[], bool] | None = None
) -> bool:
    """Start inductor's compile worker pool if it is not running and wait up to ``timeout_s``, and not once
    ``cancelled()``, until it takes jobs (Note [Compile workers]). False where it will not be used: one compile
    thread, a torch without the pool, a pool not ready in time (inductor then compiles in this thread, as before)."""
    try:
        from torch._inductor.async_compile import AsyncCompile

        if AsyncCompile.use_process_pool():  # also submits the pool's first job, which starts it
            return True
    except Exception as e:  # no such API in this torch, or the pool cannot start: inductor compiles here
        log.warning("inductor's compile workers unavailable (%s); compiling in this thread", _short(e))
        return False
    ready = getattr(AsyncCompile, "_ready_future", None)  # None: no pool (one compile thread, or not allowed)
    if ready is None:
        return False
    start = time.monotonic()
    deadline = start + timeout_s
    while not (cancelled is not None and cancelled()):
        try:
            ready.result(timeout=min(0.25, max(0.0, deadline - time.monotonic())))
            log.info("waited %.1f s for inductor's compile workers", time.monotonic() - start)
            return bool(AsyncCompile.use_process_pool())
        except FuturesTimeout:
            if time.monotonic() >= deadline:
                log.warning("inductor's compile workers not ready after %.0f s; compiling in this thread", timeout_s)
                return False
        except Exception as e:  # a pool that failed to start: inductor compiles here, as before
            log.warning("inductor's compile workers did not start (%s); compiling in this thread", _short(e))
            return False
    return False


def _short(exc: BaseException, limit: int = 600) -> str:
    text = f"{type(exc).__name__}: {exc}".strip()
    return text if len(text) <= limit else text[:limit] + " ..."


def _reset_capture_state(device: torch.device) -> None:
    """After a failed capture, bring the CUDA generator out of capture mode.

    A capture that fails half-way may never run its epilogue, leaving the device's RNG registered with the dead graph;
    every later random op in the process then fails ("Offset increment outside graph capture"). One empty capture
    runs the prologue/epilogue pair again and leaves the generator in its normal state. (Written after that failure
    was seen on an H100; this reset itself has not yet run on a GPU.)
    """
    try:
        torch.cuda.synchronize(device)
        g = torch.cuda.CUDAGraph()
        with torch.cuda.graph(g):
            pass
        del g
    except Exception:  # best effort: the original error is what the user needs to see
        pass


class CompiledExecutor(Executor):
    """``torch.compile`` of the model, compiled for batches of 1 to ``max_batch`` (Note [One compile for every batch])
    and (on CUDA) graph-captured for each at construction, before READY.

    The model is cast to the precision in place: the executor owns it from here on.
    """

    backend = "compile"
    options = CompileOptions
    opts: CompileOptions

    def _setup(self, model: Model) -> None:
        self.model = cast_model_(model, self.dtype)
        # Before anything compiles: no entry of another release is ever read (Note [Compile cache key]).
        self.compile_cache = use_compile_cache(self.cache_dir / "compile")
        self.cudagraphs = self.device.type == "cuda" and self.opts.cudagraphs
        self._keys = list(self.input_spec)
        # One buffer per key for max_batch frames; batch size b reads its first b frames, through views made once
        # here, so each batch size always sees the same tensors (Note [CUDA graphs]).
        self._full = model.example_inputs(self.device, self.max_batch)
        self._static = self._views()
        self._at = 0  # the batch size the warm-up runs
        self._graphs: dict[int, torch.cuda.CUDAGraph] = {}
        self._graph_out: dict[int, dict[str, torch.Tensor]] = {}
        self._side: torch.cuda.Stream | None = None
        self._in_graphs: list[torch.cuda.CUDAGraph] = []
        self._out_graphs: list[torch.cuda.CUDAGraph] = []
        self._raw: _RawLaunch | None = None
        self._pool_bytes = 0
        t0 = time.perf_counter()
        self._compile()
        if self.cudagraphs:
            self._capture()
        self.warmup_s = time.perf_counter() - t0
        log.info(
            "%s: compiled (%s) in %.1f s",
            self.name,
            ", ".join(f"{k}={v}" for k, v in self.describe().items()),
            self.warmup_s,
        )

    def _compiler(self, dynamic: bool) -> PrecisionRunner:
        """The compiled model, run at the precision; ``dynamic``: batches of 2 or more may share a graph (Note [One
        compile for every batch]), else every shape is fixed."""
        mode = None if self.opts.mode == "default" else "max-autotune-no-cudagraphs"
        compiled = torch.compile(
            self.model,
            fullgraph=self.opts.fullgraph,
            dynamic=None if dynamic else False,
            backend=self.opts.compiler,
            mode=mode,
        )
        return PrecisionRunner(compiled, self.output_spec, self.dtype, self.device.type)

    def _views(self) -> dict[int, dict[str, torch.Tensor]]:
        """Each batch size's static inputs: the first ``b`` frames of the buffers, new views (no marks on them)."""
        return {b: {k: self._full[k][:b] for k in self._keys} for b in range(1, self.max_batch + 1)}

    def _compile(self) -> None:
        """Note [One compile for every batch]: with a symbolic batch where ``max_batch`` > 2, each size compiled
        apart if that fails."""
        symbolic = self.max_batch > 2  # else two sizes are two graphs either way
        self._run = self._compiler(dynamic=symbolic)
        if not symbolic:
            self._warm_up()
            return
        for b, static in self._static.items():
            for t in static.values():
                for d in range(1, t.dim()):  # only the batch may vary: no other dimension turns symbolic
                    torch._dynamo.mark_static(t, d)
                if b > 1:
                    torch._dynamo.maybe_mark_dynamic(t, 0)
        try:
            self._warm_up()
        except BackendError as e:
            if self._at < 2:  # a frame alone failed: no batch to blame
                raise
            log.warning(
                "%s: compiling batches of 2 to %d with one graph failed (%s); compiling each batch size instead",
                self.name,
                self.max_batch,
                _short(e.__cause__ if e.__cause__ is not None else e),
            )
            self._run = self._compiler(dynamic=False)
            self._static = self._views()
            self._warm_up()

    def _warm_up(self) -> None:
        # A model that fixes its batch compiles each size, each a recompilation of the same forward; dynamo would fall
        # back to eager past its recompile limit (8 by default), so while they compile the limit grows by two per
        # size (each runs twice, below). (Entries of earlier, dead instances of the model may count too, when a new
        # one reuses their id.)
        # Every size runs twice: a model that fills a cache on its first call (torchvision's anchor generator) is
        # compiled for the filled cache here too, not in the middle of a stream.
        limit = torch._dynamo.config.recompile_limit + 2 * self.max_batch
        steps = self.max_batch * (3 if self.cudagraphs else 2)  # each size run twice (and captured)
        try:
            with torch._dynamo.config.patch(recompile_limit=limit), torch.inference_mode():
                for again in range(2):
                    for b, static in self._static.items():
                        self._at = b
                        self._run(static)
                        self.progress(again * self.max_batch + b, steps)
        except Exception as e:
            hint = (
                "; backend_options.fullgraph: false runs graph breaks eagerly"
                if self.opts.fullgraph and self.opts.compiler != "eager"
                else ""
            )
            raise BackendError(
                f"{self.name}: torch.compile (compiler {self.opts.compiler!r}) failed at warm-up: {_short(e)}{hint}"
            ) from e

    def _capture(self) -> None:
        cur = torch.cuda.current_stream(self.device)
        side = lend(self, self.device)  # Note [Reused streams]: a head added again captures on the same stream
        side.wait_stream(cur)
        with torch.inference_mode(), torch.cuda.stream(side):
            for static in self._static.values():
                for _ in range(self.opts.warmup_iters):
                    self._run(static)
        graphs: dict[int, torch.cuda.CUDAGraph] = {}
        outs: dict[int, dict[str, torch.Tensor]] = {}
        first: torch.cuda.CUDAGraph | None = None
        with _CAPTURE_LOCK:
            # What the pool takes: the segments reserved across the captures (held_bytes). A capture's pool only
            # ever takes new segments, and the warm-up's leftovers go back first (as each capture does).
            torch.cuda.empty_cache()
            before = torch.cuda.memory_reserved(self.device)
            # Largest batch first: the smaller graphs then fit in what its intermediates freed (Note [CUDA graphs]).
            for b, static in sorted(self._static.items(), reverse=True):
                graph = torch.cuda.CUDAGraph()
                # Every graph after the first shares the first one's pool (Note [CUDA graphs]).
                pool = first.pool() if first is not None else None
                try:
                    with (
                        torch.inference_mode(),
                        torch.cuda.graph(graph, pool=pool, stream=side, capture_error_mode="thread_local"),
                    ):
                        outs[b] = self._run(static)
                except Exception as e:
                    _reset_capture_state(self.device)
                    fix = (
                        f"The device has too little free memory for a batch of {b} (one frame of each camera the "
                        "model serves): fewer cameras, a smaller model or a lower precision"
                        if isinstance(e, torch.cuda.OutOfMemoryError)
                        else "The model synchronises with the host or has data-dependent shapes (e.g. .item(), "
                        "nonzero, NMS); set backend_options.cudagraphs: false to run it compiled without a graph"
                    )
                    raise BackendError(
                        f"{self.name}: CUDA graph capture (batch of {b}) failed: {_short(e)}. {fix}"
                    ) from e
                graphs[b] = graph
                if first is None:
                    first = graph
                self.progress(2 * self.max_batch + len(graphs), 3 * self.max_batch)
            self._pool_bytes = torch.cuda.memory_reserved(self.device) - before
            if self._pool_bytes < 0:  # another thread gave memory back meanwhile: no figure rather than a wrong one
                log.warning("%s: its CUDA graphs' pool could not be measured; stats() leaves it out", self.name)
                self._pool_bytes = 0
        cur.wait_stream(side)
        # The graphs read the weights (self.model), the static inputs and workspaces set up for the side stream in
        # place, and write the outputs into their pool: all of them must live as long as the graphs do.
        self._graphs, self._graph_out, self._side = graphs, outs, side

    def held_bytes(self) -> int:
        """The model's weights, the static inputs and the memory pool of its CUDA graphs (Note [CUDA graphs]): the
        outputs of every batch size and the room the largest one's intermediates take, reserved for good.

        The pool is what the device's allocator reserved while the graphs were captured. Builds take turns (Note
        [One build at a time]) and serving workers allocate nothing (Invariant: constant memory), so that is the
        pool's alone, but for what another thread reserves meanwhile without the build lock: an eager model beside
        it re-reserving the activations a capture's ``empty_cache`` gave back, another engine started side by
        side. Then the figure is an upper bound. (``torch.cuda.memory_snapshot(mempool_id=...)`` would read the
        pool exactly, but in torch 2.11 it crashed the process, a segmentation fault, as engines were started
        after an earlier one's graphs were freed.)"""
        held = super().held_bytes()
        if self.device.type != "cuda":
            return held
        return held + tensor_bytes(self._static[self.max_batch].values()) + self._pool_bytes

    def __call__(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        b = self._batch(inputs, self._keys)
        static = self._static[b]
        for k in self._keys:
            static[k].copy_(inputs[k], non_blocking=True)
        graph = self._graphs.get(b)
        if graph is not None:
            graph.replay()
            return dict(self._graph_out[b])
        with torch.inference_mode():
            return self._run(static)

    def bind(self, inputs: list[dict[str, torch.Tensor]], outputs: list[dict[str, torch.Tensor]]) -> bool:
        """Capture the copies from each input slot into the static inputs of the batch-of-one graph, and out of its
        static outputs into each output slot, as CUDA graphs (Note [Slot-bound runs]). A slot holds one frame with
        no batch dimension; the graph's buffers have a leading 1, so both sides of each copy are plain views. Host
        slots must be page-locked (the worker registers them); a capture that fails leaves the executor unbound,
        running as before, and says why in the log."""
        if 1 not in self._graphs or self._side is None or not self.opts.slot_bound:
            return False
        static, graph_out = self._static[1], self._graph_out[1]
        for slot in inputs:
            for k in self._keys:
                t, spec = slot.get(k), self.input_spec[k]
                if t is None or t.shape != spec.shape or t.dtype != spec.torch_dtype:
                    raise BackendError(
                        f"{self.name}: input slot tensor {k!r} is "
                        f"{'missing' if t is None else f'{t.dtype}{list(t.shape)}'}, the model reads {spec}"
                    )
        for slot in outputs:
            for k, t in slot.items():
                src = graph_out.get(k)
                if src is None or src.shape[1:] != t.shape:
                    raise BackendError(
                        f"{self.name}: output slot tensor {k!r} {list(t.shape)} does not match the model's "
                        f"output {None if src is None else list(src.shape[1:])}"
                    )
        cur = torch.cuda.current_stream(self.device)
        self._side.wait_stream(cur)
        try:
            with _CAPTURE_LOCK, torch.inference_mode():
                in_graphs = [self._copy_graph([(static[k][0], s[k]) for k in self._keys]) for s in inputs]
                out_graphs = [self._copy_graph([(t, graph_out[k][0]) for k, t in s.items()]) for s in outputs]
        except Exception as e:
            _reset_capture_state(self.device)
            log.warning("%s: running without slot-bound copies (capturing them failed: %s)", self.name, _short(e))
            return False
        finally:
            cur.wait_stream(self._side)
        self._in_graphs, self._out_graphs = in_graphs, out_graphs
        self._raw = _RawLaunch.make(self.name, self.device, self._graphs[1], in_graphs, out_graphs)
        return True

    def _copy_graph(self, pairs: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.cuda.CUDAGraph:
        assert self._side is not None
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, stream=self._side, capture_error_mode="thread_local"):
            for dst, src in pairs:
                dst.copy_(src, non_blocking=True)
        return graph

    def run_bound(self, in_index: int, out_index: int) -> None:
        self._in_graphs[in_index].replay()
        self._graphs[1].replay()
        self._out_graphs[out_index].replay()

    def run_bound_on(self, stream: torch.cuda.Stream | None, in_index: int, out_index: int) -> None:
        raw = self._raw
        if raw is not None and stream is not None and torch.cuda.current_device() == raw.device_index:
            raw.launch(stream.cuda_stream, in_index, out_index)
        else:
            super().run_bound_on(stream, in_index, out_index)

    def describe(self) -> dict[str, Any]:
        return {
            **super().describe(),
            "compiler": self.opts.compiler,
            "mode": self.opts.mode,
            "fullgraph": self.opts.fullgraph,
            "cudagraphs": bool(self._graphs),
            "slot_bound": bool(self._in_graphs),
            "raw_launch": self._raw is not None,
            "compile_cache": self.compile_cache["TORCHINDUCTOR_CACHE_DIR"],
        }


class _RawLaunch:
    """A slot-bound run's three graphs launched on a given stream with ``cudaGraphLaunch`` (CUDA Python bindings),
    so a thread need not make that stream current first: after an idle wait, switching streams around the replays
    costs 0.1 ms on an H100 VM and three raw launches a third of that (Note [Launch path] in runtime/handoff.py).

    ``CUDAGraph.replay`` also advances the CUDA generator past the random numbers the graph draws; a raw launch
    does not, so ``make`` returns None for a model graph that draws any (seen by replaying it once), and when the
    bindings are missing. The graph objects stay referenced by the executor; this holds their exec handles only."""

    def __init__(self, cudart: Any, device_index: int, model: int, ins: list[int], outs: list[int]) -> None:
        self.cudart, self.device_index = cudart, device_index
        self.model, self.ins, self.outs = model, ins, outs
        self.success = cudart.cudaError_t.cudaSuccess

    @classmethod
    def make(
        cls,
        name: str,
        device: torch.device,
        graph: torch.cuda.CUDAGraph | None,
        ins: list[torch.cuda.CUDAGraph],
        outs: list[torch.cuda.CUDAGraph],
    ) -> _RawLaunch | None:
        import importlib

        if graph is None or not hasattr(graph, "raw_cuda_graph_exec"):
            return None
        cudart = None
        for module in ("cuda.bindings.runtime", "cuda.cudart"):  # cuda-bindings >= 12.6, older cuda-python
            try:
                cudart = importlib.import_module(module)
                break
            except ImportError:
                continue
        if cudart is None:
            log.info("%s: no CUDA Python bindings; a launch from another thread switches streams", name)
            return None
        index = device.index if device.index is not None else torch.cuda.current_device()
        with torch.cuda.device(index):
            before = torch.cuda.get_rng_state(index)
            graph.replay()  # static inputs to the private pool's outputs: harmless
            torch.cuda.synchronize(index)
            draws = not torch.equal(before, torch.cuda.get_rng_state(index))
        if draws:
            log.info("%s: the model draws random numbers; a launch from another thread switches streams", name)
            return None
        return cls(
            cudart,
            index,
            graph.raw_cuda_graph_exec(),
            [g.raw_cuda_graph_exec() for g in ins],
            [g.raw_cuda_graph_exec() for g in outs],
        )

    def launch(self, stream: int, in_index: int, out_index: int) -> None:
        launch = self.cudart.cudaGraphLaunch
        for h in (self.ins[in_index], self.model, self.outs[out_index]):
            (err,) = launch(h, stream)
            if err != self.success:
                raise BackendError(f"cudaGraphLaunch failed: {err!r}")
