"""The public face: ``Engine(config)``.

::

    with Engine("configs/tiny.yaml") as engine:        # plans, allocates every buffer, starts every worker
        fid = engine.submit(frame)                      # -> frame id; bad frames raise ValueError
        out = engine.wait(fid, timeout=1.0)             # {head: Result} for that frame
        engine.set_rate("depth", 5)                     # Hz, at run time; 0 pauses
        print(engine.stats()["models"]["depth"])        # counters, achieved Hz, latencies

Every result names its head, frame id, capture time and latency. Nothing is lost silently: frames a model never saw
are counted as skipped, results nobody collected as missed, and ``stats()`` shows both.

Note [Borrowed results]
~~~~~~~~~~~~~~~~~~~~~~~
By default a result's host arrays are the caller's own copies. With ``copy=False`` (``wait``, ``results``,
``latest``) they are read-only views of the head's output slot instead: eight 1080p float32 depth maps are 66 MB a
frame, and copying them costs more than the heads' GPU time on a fast GPU. A borrowed slot is pinned by one of the
head's ``LEASES`` (2) lease readers, so the head never writes into it while anything refers to the arrays (no
torn reads); once the last array, view of one, or tensor made from one is gone, the lease goes back at the next
``wait``/``results``/``latest`` call. With every lease of a head out, further results of that head are copies
(``Result.borrowed`` says which). The mapping outlives ``stop()`` as long as a view of it does.

Note [Frame slots]
~~~~~~~~~~~~~~~~~~
``submit`` copies the caller's frame into an input slot: 6 MB for a 1080p frame, about 1 ms of memcpy, which on a
fast GPU is as long as the backbone. ``frame_slot`` lends the slot itself instead, so a camera or decoder writes the
frame there once (``cv2.VideoCapture.read(image=...)``, a driver's DMA buffer copy, a message's payload). The slot is
the writer's (state WRITING) until the with-block ends, so no reader sees a half-written frame; leaving the block
publishes it exactly as ``submit`` would (same frame ids, counters and skip accounting), and an exception or
``cancel()`` gives it back unpublished. The submit lock is held for the whole block: frames enter the engine in one
order, from one writer at a time.
"""

from __future__ import annotations

import collections
import functools
import logging
import shutil
import sys
import tempfile
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np
import torch

from vpengine import checks
from vpengine.boundary import Boundary, Placement
from vpengine.config import EngineConfig, load_config
from vpengine.models.preprocess import IMAGENET_MEAN
from vpengine.runtime.control import NOT_SERVING, POLL_S, ControlBlock
from vpengine.runtime.fence import MappingFence
from vpengine.runtime.handoff import Handoffs
from vpengine.runtime.plan import Plan, make_plan
from vpengine.runtime.supervisor import EngineDeadError, EngineStartError, Runner, log_to_file
from vpengine.runtime.worker import WorkerSpec
from vpengine.transport.layout import SlotLayout
from vpengine.transport.memory import free_bytes
from vpengine.transport.ring import Accept, ReaderDecl, RingReader, SlotInfo, SlotRing

log = logging.getLogger("vpengine")

__all__ = ["Engine", "EngineDeadError", "EngineStartError", "FrameSlot", "Result"]

_ORIGINS_KEPT = 8192
_RECYCLED_PER_OUTPUT = 2  # host arrays kept per (head, output) for reuse once the user has let go of them
LEASES = 2  # results of each head a caller may hold without a copy (Note [Borrowed results])


_F = TypeVar("_F", bound=Callable[..., Any])


def _fenced(method: _F) -> _F:
    """An API method that runs inside the engine's fence: what it touches stays mapped until it returns, and once
    ``stop()`` has begun it raises EngineDeadError (Note [Unmapping at stop] in runtime/fence.py)."""

    @functools.wraps(method)
    def call(self: Engine, *args: Any, **kw: Any) -> Any:
        with self._res.fence:
            return method(self, *args, **kw)

    return cast(_F, call)


def _refcounts(pool: list[np.ndarray]) -> list[int]:
    return [sys.getrefcount(a) for a in pool]


# what _refcounts reports for an array that only the pool list refers to (differs between Python versions)
_FREE_REFS = _refcounts([np.empty(1)])[0]


class _HostOutputs:
    """Host arrays for results, recycled: copying a 1080p float32 depth map into fresh memory costs page faults on
    every frame (eight of them are 66 MB), so an array is reused once nothing outside this pool refers to it
    (a view or a tensor made from it refers to it too). Bounded: at most ``_RECYCLED_PER_OUTPUT`` arrays per
    output are kept; beyond that results get fresh arrays that are not tracked."""

    def __init__(self) -> None:
        self._pools: dict[tuple[str, str], list[np.ndarray]] = {}

    def copy(self, head: str, key: str, src: np.ndarray) -> np.ndarray:
        pool = self._pools.setdefault((head, key), [])
        for arr, refs in zip(pool, _refcounts(pool)):
            if refs <= _FREE_REFS and arr.shape == src.shape and arr.dtype == src.dtype:
                np.copyto(arr, src)
                return arr
        arr = src.copy()
        if len(pool) < _RECYCLED_PER_OUTPUT:
            pool.append(arr)
        return arr


def _numpy_output(t: torch.Tensor) -> bool:
    """Whether an output slot tensor is handed out as a numpy array (host, and a dtype numpy has), not a tensor."""
    return t.device.type == "cpu" and t.dtype != torch.bfloat16


class _Lease:
    """Keeps a borrowed slot pinned: every array of a borrowed result refers to it; when the last one goes, its
    finalizer hands the lease reader back (queued, not released there: a finalizer may run inside a ring's critical
    section of this very thread, whose mutex is not re-entrant)."""

    __slots__ = ("__weakref__", "mapping")

    def __init__(self, mapping: object) -> None:
        self.mapping = mapping  # keeps the slot's memory mapped, even past stop()


class _SlotView:
    """What ``np.asarray`` turns into a read-only array over a slot tensor; the array's base, holding the lease."""

    __slots__ = ("__array_interface__", "_lease")

    def __init__(self, iface: dict[str, Any], lease: _Lease) -> None:
        self.__array_interface__ = iface
        self._lease = lease


def _read_only_interface(tensor: torch.Tensor) -> dict[str, Any]:
    iface = dict(tensor.numpy().__array_interface__)
    iface["data"] = (iface["data"][0], True)  # read-only
    return iface


class _Leases:
    """Lease readers of every head's output ring (Note [Borrowed results])."""

    def __init__(self, readers: dict[str, list[RingReader]]) -> None:
        self.free = {h: list(rs) for h, rs in readers.items()}
        self.total = {h: len(rs) for h, rs in readers.items()}
        self.returned: collections.deque[tuple[str, RingReader]] = collections.deque()
        # (head, slot index) -> key -> array interface: a slot's tensors never move, and borrowing runs right after
        # the caller wakes, where every call costs several times what it does in a loop (Note [Launch path])
        self._interfaces: dict[tuple[str, int], dict[str, dict[str, Any]]] = {}

    def drain(self) -> None:
        """Release the slots whose results nobody refers to any more (caller holds the engine's read lock)."""
        while self.returned:
            head, reader = self.returned.popleft()
            reader.release()
            self.free[head].append(reader)

    def borrow(self, head: str, slot: SlotInfo) -> dict[str, np.ndarray] | None:
        """Read-only arrays over ``slot`` (pinned by the caller's reader), or None if no lease is free."""
        free = self.free.get(head)
        if not free:
            return None
        reader = free[-1]
        held = reader.pin_slot(slot)
        if held is None:
            return None
        free.pop()
        lease = _Lease(reader.ring.data_region.keep_mapped())
        weakref.finalize(lease, self.returned.append, (head, reader))
        ifaces = self._interfaces.get((head, held.index))
        if ifaces is None:
            ifaces = {k: _read_only_interface(t) for k, t in held.tensors.items()}
            self._interfaces[(head, held.index)] = ifaces
        return {k: np.asarray(_SlotView(iface, lease)) for k, iface in ifaces.items()}

    def held(self, head: str) -> int:
        return self.total[head] - len(self.free[head])


@dataclass
class Result:
    """One head's output for one frame."""

    head: str
    frame_id: int
    #: The frame's capture time as given to submit (or the wall-clock time of submit), seconds since the epoch.
    capture_time: float
    #: Seconds from submit to this output being on the host (published, and its device work done).
    latency: float
    #: Output tensors: numpy arrays (host outputs) or torch tensors (device outputs, bfloat16). A host array's memory
    #: is reused for a later result of the same head once nothing refers to the array (nor to any view of it) any
    #: more, so keeping a reference (or a view, or ``torch.from_numpy`` of it) keeps its content.
    outputs: dict[str, Any]
    seq: int = 0
    #: When the output was there to read (``time.monotonic()``).
    t_publish: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)
    #: True: the host arrays are read-only views of the head's output slot, kept for as long as they are referenced
    #: (Note [Borrowed results]); False: they are copies.
    borrowed: bool = False
    #: (height, width) of the submitted frame.
    frame_size: tuple[int, int] = (0, 0)
    #: "frame": maps at the frame's size, boxes in its pixels (the default); "native": in the models' input grid,
    #: as the head's ``output.grid: native`` asks (Note [Frame grid] in boundary.py).
    grid: str = "frame"
    #: Where the frame lies in the models' input grid; maps native outputs to the frame's grid.
    placement: Placement | None = None
    #: The frame itself, for results of ``Engine.predict`` (others: None; the engine keeps no frames).
    image: np.ndarray | None = None
    #: The head's metadata (kind, labels, palette), for drawing.
    info: dict[str, Any] = field(default_factory=dict, repr=False)

    def __getitem__(self, key: str) -> Any:
        return self.outputs[key]

    def plot(self, image: np.ndarray | None = None) -> np.ndarray:
        """This result drawn as a BGR uint8 picture at its frame's size: on ``image`` (or the predicted frame,
        ``self.image``) when given, else on its own (depth colours with a bar, class colours, boxes on black)."""
        from vpengine.io.visualize import draw_result

        frame = self.image if image is None else image
        if frame is None and self.info.get("kind") == "detection":
            frame = np.zeros((*self.frame_size, 3), np.uint8)
        return draw_result(frame, self, self.info, self.head)


class _Resources:
    """What must be released even if the user forgets stop(): workers, mailboxes, control block. Refers to nothing
    that refers to the Engine, so that an Engine nobody refers to is collected and this is closed by its finalizer."""

    def __init__(self) -> None:
        self.runner: Runner | None = None
        self.rings: dict[str, SlotRing] = {}
        self.control: ControlBlock | None = None
        self.dirs: list[str] = []  # private temporary directories (e.g. the no-MPS pipe directory)
        self.fence = MappingFence()  # Note [Unmapping at stop]
        self.log_file: logging.Handler | None = None

    def close(self) -> list[str]:
        forced: list[str] = []
        if self.runner is not None:
            forced = self.runner.stop()
            for thread in self.runner.threads_alive():  # abandoned workers: unmap once they are gone
                self.fence.hold_until_gone(thread)
            self.runner = None
        if self.log_file is not None:
            logging.getLogger("vpengine").removeHandler(self.log_file)
            self.log_file.close()
            self.log_file = None
        for d in self.dirs:
            shutil.rmtree(d, ignore_errors=True)
        self.dirs = []
        self.fence.close(self._unmap)  # Note [Unmapping at stop]: now, or once the last user is gone
        return forced

    def _unmap(self) -> None:
        for ring in self.rings.values():
            ring.close()
        self.rings = {}
        if self.control is not None:
            self.control.close()
            self.control = None


def _worker_env(cfg: EngineConfig, mps_dir: str | None, nomps_dir: str, name: str) -> dict[str, str]:
    """Environment overrides for a worker process, decided at each (re)start."""
    if torch.device(cfg.device).type != "cuda":
        return {}
    from vpengine.runtime import mps

    use = mps_dir if mps_dir and mps.status(mps_dir)["reachable"] else None
    env = {"CUDA_MPS_PIPE_DIRECTORY": use or nomps_dir}
    if use:
        mcfg = cfg.foundation_model if name == "foundation" else cfg.head(name)
        env["CUDA_MPS_CLIENT_PRIORITY"] = "1" if mcfg.mps_priority == "below_normal" else "0"
    elif mps_dir:
        log.warning("MPS daemon at %s no longer answers: %s starts without MPS", mps_dir, name)
    return env


class FrameSlot:
    """An input slot lent by ``Engine.frame_slot``: write the frame into ``array``, then leave the with-block."""

    def __init__(
        self, engine: Engine, frame_id: int | None, timestamp: float | None, size: tuple[int, int] | None
    ) -> None:
        self._engine = engine
        # capture time in seconds; may be set inside the block (default: when it ends)
        self.timestamp = timestamp
        self._frame_id_arg = frame_id
        self._size = size
        self.frame_id: int | None = None  # set when the block ends and the frame is submitted
        self._array: np.ndarray | None = None
        self._slot: SlotInfo | None = None
        self._cancelled = False

    @property
    def array(self) -> np.ndarray | None:
        """The writable frame: ``(height, width, 3)`` of the input dtype (None outside the block)."""
        return self._array

    @array.setter
    def array(self, value: np.ndarray) -> None:
        """``ok, slot.array = cap.read(image=slot.array)``: what a writer hands back must be the lent array itself.
        A writer that allocated a new array instead (OpenCV does when the sizes differ) wrote nothing into the
        slot: refused, naming both sizes, rather than submitting whatever the slot held before."""
        arr = self._array
        if arr is None:
            raise RuntimeError("a FrameSlot's array exists only inside its with-block")
        if not isinstance(value, np.ndarray) or value.__array_interface__["data"][0] != arr.ctypes.data:
            got = (
                f"{value.shape[1]}x{value.shape[0]}"
                if isinstance(value, np.ndarray) and value.ndim >= 2
                else (type(value).__name__)
            )
            raise ValueError(
                f"the frame was written into a new {got} array, not into the {arr.shape[1]}x{arr.shape[0]} slot "
                f"(a writer allocates one when the sizes differ): open the slot with frame_slot(size=(height, width)) "
                "of your frames"
            )
        if value.shape != arr.shape or value.dtype != arr.dtype:
            raise ValueError(
                f"the frame written is {value.shape} {value.dtype}, the slot {arr.shape} {arr.dtype}: open the slot "
                "with frame_slot(size=(height, width)) of your frames"
            )

    def cancel(self) -> None:
        """Submit nothing when the block ends (e.g. the camera returned no frame)."""
        self._cancelled = True

    def __enter__(self) -> FrameSlot:
        eng = self._engine
        if self._slot is not None or self.frame_id is not None or self._cancelled:
            raise RuntimeError("a FrameSlot is used for one with-block; call engine.frame_slot() again")
        fence = eng._res.fence
        fence.__enter__()  # the slot is mapped memory: held for the whole block (Note [Unmapping at stop])
        eng._submit_lock.acquire()
        try:
            eng._require_running()
            slot = eng._acquire_input()
        except BaseException:
            eng._submit_lock.release()
            fence.leave()
            raise
        eng._filling = threading.get_ident()
        self._slot = slot
        # the slot itself when the frames are the models' size; else a buffer the frame is fitted from at the end
        # (Note [Frame grid] in boundary.py)
        self._array = eng._frame_views[slot.index] if self._size is None else eng._staging(self._size)
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        eng, slot, arr = self._engine, self._slot, self._array
        assert slot is not None and arr is not None
        self._array, self._slot = None, None  # the slot is the engine's again: no writes after the block
        try:
            if exc_type is not None or self._cancelled or eng._state != "running":
                eng._input_writer.abort(slot)
                return
            t_submit = time.monotonic()
            try:
                stamp = checks.timestamp(self.timestamp)  # may have been set inside the block
            except ValueError:
                eng._input_writer.abort(slot)
                raise
            t_capture = time.time() if stamp is None else stamp
            if self._size is None:
                placement = eng.boundary.placement(arr.shape[:2])
            else:
                try:
                    placement = eng.boundary.write(eng.boundary.check(arr), eng._frame_views[slot.index])
                except BaseException:
                    eng._input_writer.abort(slot)
                    raise
            self.frame_id = eng._publish_input(slot, self._frame_id_arg, t_capture, t_submit, placement)
        finally:
            eng._filling = None
            eng._submit_lock.release()
            eng._res.fence.leave()


class Engine:
    """One foundation model shared by many heads. See the module docstring for a tour."""

    def __init__(
        self,
        config: EngineConfig | str | Path | dict[str, Any] | None = None,
        overrides: list[str] | None = None,
    ) -> None:
        self.config = load_config(config, overrides)
        self.plan: Plan = make_plan(self.config)
        self._res = _Resources()
        self._finalizer = weakref.finalize(self, _Resources.close, self._res)
        self._state = "planned"
        self._submit_lock = threading.Lock()
        self._filling: int | None = None  # thread id holding an open frame_slot (and _submit_lock)
        self._read_lock = threading.Lock()
        self._next_id = 0
        self._submitted = 0
        self._rejected = 0
        self._origins: collections.OrderedDict[int, int] = collections.OrderedDict()
        # input seq -> where the frame lies in the input canvas (Note [Frame grid] in boundary.py)
        self._placements: collections.OrderedDict[int, Placement] = collections.OrderedDict()
        self.boundary = Boundary(
            self.config,
            {h: (m.meta, m.output_spec) for h, m in self.plan.heads.items()},
            self.plan.foundation.meta.get("normalize_mean", IMAGENET_MEAN),
        )
        self._staged: dict[tuple[int, int], np.ndarray] = {}
        self._results_active = False
        self._pool: Any = None
        self._host_outputs = _HostOutputs()
        self._numpy_heads: dict[str, bool] = {}  # head -> its outputs are handed out as numpy arrays
        self._t_start = 0.0
        self.memory_report: dict[str, Any] = {}
        self._mps_dir: str | None = None
        self._nomps_dir = ""
        self._finalizer_dirs = self._res.dirs
        self._handoffs = Handoffs()  # thread mode: replaced at start (runtime/handoff.py)

    # ------------------------------------------------------------------------------------------ lifecycle
    def start(self) -> Engine:
        if self._state != "planned":
            raise RuntimeError(f"engine is {self._state}; an Engine starts once")
        cfg, plan = self.config, self.plan
        device = torch.device(cfg.device)
        shared = cfg.mode == "process"
        heads = list(plan.heads)
        res = self._res
        try:
            if device.type == "cuda":
                self._prepare_cuda(device, shared)
            mailboxes = self._mailboxes(device, shared)
            self._check_preallocation(mailboxes)  # before any of it is allocated
            for m in mailboxes:
                res.rings[m["name"]] = SlotRing.create(**m)
            if cfg.logging.file:
                res.log_file = log_to_file(cfg.logging.file, cfg.logging.level, "engine")
            res.control = ControlBlock.create(cfg.model_names())
            res.control.set_rate("foundation", cfg.foundation_model.rate_hz)
            for h in cfg.heads:
                res.control.set_rate(h.name, h.rate_hz)
            specs = self._worker_specs()
            if shared:
                from vpengine.runtime.process import ProcessRunner

                # not a bound method: the runner must not refer to the Engine (see _Resources)
                env_for = functools.partial(_worker_env, cfg, self._mps_dir, self._nomps_dir)
                res.runner = ProcessRunner(specs, res.rings, res.control, cfg, env_for=env_for)
            else:
                from vpengine.runtime.handoff import make_handoffs
                from vpengine.runtime.threads import ThreadRunner

                self._handoffs = make_handoffs(res.rings, heads, device.type == "cuda")
                res.runner = ThreadRunner(specs, res.rings, res.control, cfg, handoffs=self._handoffs)
            res.runner.start()
        except BaseException:
            self._state = "stopped"
            res.close()
            raise
        self._input_writer = res.rings["input"].writer()
        self._frame_views = [v["frame"].numpy() for v in res.rings["input"].views]
        self._results_readers = {h: res.rings[f"out.{h}"].reader("results") for h in heads}
        self._peek_readers = {h: res.rings[f"out.{h}"].reader("peek") for h in heads}
        self._leases = _Leases(
            {
                h.name: [res.rings[f"out.{h.name}"].reader(f"lease{i}") for i in range(LEASES)]
                for h in cfg.heads
            }
        )
        self._t_start = time.monotonic()
        self._state = "running"
        self.memory_report = self._memory_report()
        log.info(
            "engine %r running: %s mode on %s, foundation %s + heads %s; mailboxes %.1f MB host, %.1f MB device",
            cfg.name,
            cfg.mode,
            cfg.device,
            cfg.foundation_model.model,
            heads,
            self.memory_report["mailbox_host_bytes"] / 1e6,
            self.memory_report["mailbox_device_bytes"] / 1e6,
        )
        return self

    def _prepare_cuda(self, device: torch.device, shared: bool) -> None:
        """Check the device, find the MPS daemon, and initialise CUDA here (in the parent) off MPS.

        See Note [MPS and ownership of device memory] in runtime/mps.py.
        """
        from vpengine.runtime import mps

        cfg = self.config
        if not torch.cuda.is_available():
            raise EngineStartError(f"device {cfg.device!r} was asked for but PyTorch sees no CUDA device")
        index = device.index or 0
        if index >= torch.cuda.device_count():
            raise EngineStartError(
                f"device {cfg.device!r}: only {torch.cuda.device_count()} CUDA device(s) visible"
            )
        self._mps_dir = mps.find_daemon() if cfg.mps != "off" else None
        if cfg.mps == "required" and self._mps_dir is None:
            raise EngineStartError(
                f"mps: required, but no MPS control daemon answers in {mps.candidate_dirs()}; "
                "start one with `vpengine mps start` or set mps: auto"
            )
        if not torch.cuda.is_initialized():
            with mps.off_mps():
                torch.cuda.init()
                torch.cuda.set_device(index)
                torch.empty(1, device=device)  # create the context now, while MPS is out of reach
        if shared:
            from vpengine.transport.cuda_vmm import CudaVmmError, vmm_support

            try:
                support = vmm_support(index)
            except CudaVmmError as e:
                raise EngineStartError(str(e)) from None
            if not all(support.values()):
                raise EngineStartError(
                    f"{cfg.device} cannot share device memory between processes through the CUDA VMM API "
                    f"({support}); use mode: thread"
                )
        self._nomps_dir = tempfile.mkdtemp(prefix="vpengine-nomps-")
        self._finalizer_dirs.append(self._nomps_dir)
        if self._mps_dir:
            log.info("CUDA MPS daemon found at %s: model workers will be MPS clients", self._mps_dir)

    def _mailboxes(self, device: torch.device, shared: bool) -> list[dict[str, Any]]:
        """``SlotRing.create``'s arguments for every mailbox: the input, the features, one output per head."""
        cfg, plan = self.config, self.plan
        gpu = device.type == "cuda"  # host rings a GPU copies from or to are page-locked
        fifo_margin = 4 if any(h.input_mode == "fifo" for h in cfg.heads) else 0
        mailboxes: list[dict[str, Any]] = [
            dict(
                name="input",
                specs=plan.frame_spec,
                n_slots=7 if cfg.foundation_model.input_mode == "fifo" else 3,
                readers=[ReaderDecl("foundation", cfg.foundation_model.input_mode)],
                device="cpu",
                shared=shared,
                pinned=gpu,
            ),
            dict(
                name="features",
                specs=plan.features,
                n_slots=max(3, len(cfg.heads) + 2 + fifo_margin),
                readers=[ReaderDecl(h.name, h.input_mode) for h in cfg.heads],
                device=device,
                shared=shared,
            ),
        ]
        for h in cfg.heads:
            leases = [ReaderDecl(f"lease{i}", active=False) for i in range(LEASES)]
            mailboxes.append(
                dict(
                    name=f"out.{h.name}",
                    specs=plan.heads[h.name].output_spec,
                    n_slots=h.output.slots + LEASES,
                    readers=[ReaderDecl("results", "fifo", active=False), ReaderDecl("peek"), *leases],
                    device=device if h.output.location == "device" else "cpu",
                    shared=shared,
                    overflow=h.output.overflow,
                    pinned=gpu,
                )
            )
        return mailboxes

    def _check_preallocation(self, mailboxes: list[dict[str, Any]]) -> None:
        """Refuse mailboxes that do not fit the memory free now, naming their size (rather than failing in the
        middle of allocating them, or leaving the machine swapping)."""
        need: dict[str, dict[str, int]] = {}  # device -> mailbox -> bytes
        for m in mailboxes:
            nbytes = SlotLayout.from_specs(m["specs"], m["n_slots"]).total_bytes
            need.setdefault(str(torch.device(m["device"])), {})[m["name"]] = nbytes
        def size(b: float) -> str:
            return f"{b / 1e9:.2f} GB" if b >= 1e9 else f"{b / 1e6:.1f} MB"

        for dev, sizes in need.items():
            total, free = sum(sizes.values()), free_bytes(torch.device(dev))
            if free is not None and total > free:
                biggest = ", ".join(f"{n} {size(b)}" for n, b in sorted(sizes.items(), key=lambda x: -x[1])[:3])
                raise EngineStartError(
                    f"the mailboxes need {size(total)} of {'host' if dev == 'cpu' else dev} memory ({biggest}), "
                    f"but only {size(free)} is free; lower input.height/width, output.slots or "
                    "the number of heads"
                )

    def _worker_specs(self) -> list[WorkerSpec]:
        cfg, plan, rings = self.config, self.plan, self._res.rings
        dump = cfg.model_dump(mode="json")
        specs = [
            WorkerSpec(
                name="foundation",
                role="foundation",
                config=dump,
                upstream=plan.frame_spec,
                upstream_meta={},
                in_ring=rings["input"].desc,
                in_reader="foundation",
                out_ring=rings["features"].desc,
                notify_output=False,
            )
        ]
        for name in plan.heads:
            specs.append(
                WorkerSpec(
                    name=name,
                    role="head",
                    config=dump,
                    upstream=plan.features,
                    upstream_meta=plan.feature_meta,
                    in_ring=rings["features"].desc,
                    in_reader=name,
                    out_ring=rings[f"out.{name}"].desc,
                    notify_output=True,
                )
            )
        return specs

    def _memory_report(self) -> dict[str, Any]:
        rings = self._res.rings
        per = {
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
        ctl = self._res.control
        workers = {n: ctl.get(n, "device_mem_bytes") for n in ctl.names} if ctl else {}
        report: dict[str, Any] = {
            "mailboxes": per,
            "mailbox_host_bytes": host,
            "mailbox_device_bytes": dev,
            "workers_torch_reserved_bytes": workers,
        }
        device = torch.device(self.config.device)
        if device.type == "cuda" and ctl is not None:
            from vpengine.runtime.gpu import process_memory

            by_pid = process_memory(device.index or 0)  # as the driver reports it (contexts included)
            if by_pid:
                import os

                pids = {n: ctl.get(n, "pid") for n in ctl.names}
                report["driver_bytes"] = {n: by_pid.get(p) for n, p in pids.items()}
                report["driver_bytes"]["engine (parent)"] = by_pid.get(os.getpid())
        return report

    def stop(self) -> None:
        """Stop every worker and free every buffer. Always returns (within stop_timeout_s + a few seconds)."""
        if self._state == "stopped":
            return
        self._state = "stopped"
        forced = self._finalizer()  # runs _Resources.close exactly once
        if forced:
            log.warning("stopped; workers %s had to be terminated", forced)

    def __enter__(self) -> Engine:
        if self._state == "planned":
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._state == "running"

    def _require_running(self) -> None:
        if self._state != "running":
            raise EngineDeadError(
                f"engine is {self._state}; call start() first"
                if self._state == "planned"
                else "engine is stopped"
            )
        ctl = self._res.control
        if ctl is not None and ctl.state("foundation") == "failed":
            raise EngineDeadError(f"the foundation model has failed for good: {ctl.last_error('foundation')}")

    # -------------------------------------------------------------------------------------------- input
    @_fenced
    def submit(self, frame: Any, frame_id: int | None = None, timestamp: float | None = None) -> int:
        """Hand a frame to the engine. Returns its frame id (``frame_id`` or the next integer).

        ``frame``: HxWx3 of the input dtype and colour order, of any size up to ``input.max_frame_side``; every
        output for it comes back in its pixel grid (Note [Frame grid] in boundary.py). ``timestamp`` is the capture
        time in seconds (e.g. the camera's stamp; default: now): rate limits run on these stamps, so a file's frames
        stamped by their position obey them however fast they are fed. Never blocks on the models: if the
        foundation model is busy, the newest frame wins and the overwritten one is counted as skipped. Raises
        ValueError naming what was expected if the frame is not an image.
        """
        self._require_running()
        try:
            arr = self.boundary.check(frame)
            frame_id, timestamp = checks.frame_id(frame_id), checks.timestamp(timestamp)
        except ValueError:
            self._rejected += 1
            raise
        t_submit = time.monotonic()
        t_capture = time.time() if timestamp is None else float(timestamp)
        self._refuse_inside_frame_slot()
        with self._submit_lock:
            slot = self._acquire_input()
            try:  # an error gives the slot back: a leaked slot is a frame the ring never gets again
                placement = self.boundary.write(arr, self._frame_views[slot.index])
                return self._publish_input(slot, frame_id, t_capture, t_submit, placement)
            except BaseException:
                self._input_writer.abort(slot)
                raise

    @_fenced
    def frame_slot(
        self, frame_id: int | None = None, timestamp: float | None = None, size: tuple[int, int] | None = None
    ) -> FrameSlot:
        """The next input slot, to write a frame into in place: ``submit`` without its copy (Note [Frame slots]).

        ::

            with engine.frame_slot(size=(h, w)) as slot:   # (h, w): the camera's frames
                ok, slot.array = cap.read(image=slot.array)   # decoded straight into the input mailbox
                if not ok:
                    slot.cancel()                    # nothing is submitted
            fid = slot.frame_id                      # set when the block ends: the frame is submitted then

        ``slot.array`` is a writable ``(height, width, 3)`` array of the configured dtype: the input mailbox slot
        itself, or, with ``size=(height, width)`` other than the models' input size, a buffer kept for frames of that
        size, fitted into the slot when the block ends (Note [Frame grid] in boundary.py). Its content is whatever
        an earlier frame left there until you write it. Assign what a writer hands back to ``slot.array``
        (``ok, slot.array = cap.read(image=slot.array)``): a writer that allocated a new array instead of writing
        into it (OpenCV does when the sizes differ) raises ValueError naming both sizes. Leaving the block submits
        it (latency counts from there); an exception inside the block or ``cancel()`` gives the slot back and
        submits nothing. One slot is open at a time: other threads' ``submit``/``frame_slot`` calls wait for it to
        close, so fill it promptly (a camera read, a decode); calling them from inside the block raises
        RuntimeError.
        """
        self._require_running()
        self._refuse_inside_frame_slot()
        if size is not None:
            h, w = (int(v) for v in size)
            if not (0 < h <= self.boundary.max_side and 0 < w <= self.boundary.max_side):
                raise ValueError(
                    f"frame_slot size {size!r}: height and width must be 1..{self.boundary.max_side} (input.max_frame_side)"
                )
            size = None if (h, w) == self.boundary.canvas_hw else (h, w)
        return FrameSlot(self, checks.frame_id(frame_id), checks.timestamp(timestamp), size)

    def _staging(self, size: tuple[int, int]) -> np.ndarray:
        """The buffer ``frame_slot(size=...)`` lends for frames of another size: one per size, kept."""
        buf = self._staged.get(size)
        if buf is None:
            buf = self._staged[size] = np.zeros((*size, 3), self.boundary.dtype)
        return buf

    def _refuse_inside_frame_slot(self) -> None:
        if self._filling == threading.get_ident():
            raise RuntimeError("a frame_slot is open in this thread: submit after its with-block ends")

    def _acquire_input(self) -> SlotInfo:
        """The input slot to fill next; the caller holds ``_submit_lock``."""
        slot = self._input_writer.acquire()
        assert slot is not None  # input ring is drop_oldest with n_slots >= readers + 2
        return slot

    def _publish_input(
        self, slot: SlotInfo, frame_id: int | None, t_capture: float, t_submit: float, placement: Placement
    ) -> int:
        """Publish a filled input slot; the caller holds ``_submit_lock``."""
        fid = self._next_id if frame_id is None else int(frame_id)
        self._next_id = fid + 1
        # known before the frame is visible (this is the ring's one writer): its results may come back at once
        self._placements[self._input_writer.ring.last_seq + 1] = placement
        if len(self._placements) > _ORIGINS_KEPT:
            self._placements.popitem(last=False)
        inline = self._handoffs.inline
        if inline is not None:  # thread mode: queue the foundation's work from here (Note [Inline launch])
            seq = inline.publish(self._input_writer, slot, fid, t_capture, t_submit)
        else:
            seq = self._input_writer.publish(slot, fid, t_capture, t_submit)
        self._submitted += 1
        self._origins[fid] = seq
        if len(self._origins) > _ORIGINS_KEPT:
            self._origins.popitem(last=False)
        return fid

    # ------------------------------------------------------------------------------------------- output
    def _borrow(self, head: str, slot: SlotInfo) -> dict[str, np.ndarray] | None:
        """Read-only arrays over pinned ``slot``'s host outputs (Note [Borrowed results]), or None (no lease free,
        or an output that is not a numpy array). Their content is there only once ``wait_done`` says so."""
        numpy = self._numpy_heads.get(head)
        if numpy is None:  # a head's outputs are host arrays, or not, in every slot
            numpy = self._numpy_heads[head] = all(_numpy_output(t) for t in slot.tensors.values())
        if not numpy or self._grid_change(head, slot) is not None:
            return None  # outputs mapped to another grid are new arrays: nothing to lend
        return self._leases.borrow(head, slot)

    def _grid_change(self, head: str, slot: SlotInfo) -> Placement | None:
        """The placement to map ``head``'s output in ``slot`` back to its frame's grid, or None (same grid, or the
        head keeps the native grid)."""
        p = self._placements.get(slot.origin)
        if p is None:  # pragma: no cover - kept for _ORIGINS_KEPT frames, far more than any mailbox holds
            raise RuntimeError(f"no record of the frame behind {head}'s output for frame {slot.frame_id}")
        return None if p.identity or head in self.boundary.native else p

    def _done_filter(self, head: str) -> Accept | None:
        """Note [Result hand-off]: the pin filter that takes only ``head``'s results whose device work is done."""
        events = self._handoffs.results.get(head)
        return None if events is None else events.done

    def _to_result(self, head: str, slot: SlotInfo, borrowed: dict[str, np.ndarray] | None = None) -> Result:
        """``head``'s result from pinned ``slot`` once its device work is done: ``borrowed``, ``_borrow``'s arrays
        (taken before the wait), or else copied."""
        # Note [Result hand-off]
        events = self._handoffs.results.get(head)
        t_ready = slot.t_publish if events is None else events.wait_done(slot)
        outputs: dict[str, Any]
        change = self._grid_change(head, slot)
        if borrowed is not None:
            outputs = borrowed
        elif change is not None:  # Note [Frame grid]: mapped straight out of the slot, into new arrays
            kinds = self.boundary.kinds[head]
            outputs = {}
            for k, t in slot.tensors.items():
                v = t.numpy() if _numpy_output(t) else t
                if k in kinds:
                    outputs[k] = change.to_frame(kinds[k], v)
                else:
                    outputs[k] = (
                        self._host_outputs.copy(head, k, v) if isinstance(v, np.ndarray) else t.clone()
                    )
        else:
            outputs = {
                k: self._host_outputs.copy(head, k, t.numpy()) if _numpy_output(t) else t.clone()
                for k, t in slot.tensors.items()
            }
        if all(isinstance(v, np.ndarray) for v in outputs.values()):
            outputs = self.plan.heads[head].finalize(outputs)
        p = self._placements[slot.origin]
        return Result(
            head,
            slot.frame_id,
            slot.t_capture,
            t_ready - slot.t_submit,
            outputs,
            slot.seq,
            t_ready,
            borrowed=borrowed is not None,
            frame_size=p.frame_hw,
            grid="native" if head in self.boundary.native else "frame",
            placement=p,
            info=self.plan.heads[head].meta,
        )

    def _copy_out(self, pinned: list[tuple[str, SlotInfo]], copy: bool = True) -> dict[str, Result]:
        """Results for pinned slots. Borrowed ones are borrowed before any is waited for, so that what can be done
        while the device finishes is done by then. Several heads' outputs are copied at once (numpy releases the
        GIL), which matters with many full-resolution outputs: eight 1080p float32 depth maps are 64 MB per frame."""
        small = sum(t.nbytes for _, s in pinned for t in s.tensors.values()) < 4 << 20
        if not copy or len(pinned) <= 1 or small:
            borrowed = [None if copy else self._borrow(h, s) for h, s in pinned]
            return {h: self._to_result(h, s, b) for (h, s), b in zip(pinned, borrowed)}
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(
                max_workers=min(8, len(self.plan.heads)), thread_name_prefix="vpe-copy"
            )
            self._finalizer_pool = weakref.finalize(self, self._pool.shutdown, wait=False)
        futures = {h: self._pool.submit(self._to_result, h, s) for h, s in pinned}
        return {h: f.result() for h, f in futures.items()}

    def _head(self, head: str) -> str:
        if head not in self.plan.heads:
            raise KeyError(f"no head named {head!r}; heads: {list(self.plan.heads)}")
        return head

    @_fenced
    def latest(self, head: str, copy: bool = True) -> Result | None:
        """The newest output of ``head``, or None if it has produced nothing yet. ``copy=False``: borrowed, not
        copied, while a lease is free (Note [Borrowed results])."""
        self._require_running()
        reader = self._peek_readers[self._head(head)]
        with self._read_lock:
            self._leases.drain()
            slot = reader.pin(peek=True, accept=self._done_filter(head))
            if slot is None:
                return None
            try:
                return self._to_result(head, slot, None if copy else self._borrow(head, slot))
            finally:
                reader.release(slot)

    @_fenced
    def results(
        self, timeout: float = 0.0, heads: list[str] | None = None, copy: bool = True
    ) -> list[Result]:
        """Every output published since the previous call, oldest first; waits up to ``timeout`` for at least one.

        The first call starts the stream (earlier outputs are not returned). Call it regularly: if it falls
        more than ``output.slots`` behind, the oldest unread outputs are overwritten and counted as missed in
        ``stats()["results"]`` (or the head waits, with ``output.overflow: block``). ``copy=False``: results are
        borrowed, not copied, while a lease is free (Note [Borrowed results]).
        """
        self._require_running()
        timeout = checks.timeout(timeout)
        ctl = self._res.control
        assert ctl is not None
        names = [self._head(h) for h in heads] if heads else list(self._results_readers)
        deadline = time.monotonic() + timeout
        with self._read_lock:
            self._leases.drain()
            if not self._results_active:
                for r in self._results_readers.values():
                    r.activate(from_now=True)
                self._results_active = True
            while True:
                word = ctl.output_word()
                out: list[Result] = []
                more = list(names)
                while more:  # one slot per head at a time (a reader holds one pin), heads copied in parallel
                    pinned: list[tuple[str, SlotInfo]] = []
                    try:
                        for h in more:
                            slot = self._results_readers[h].pin(accept=self._done_filter(h))
                            if slot is not None:
                                pinned.append((h, slot))
                        out.extend(self._copy_out(pinned, copy).values())
                    finally:
                        for h, slot in pinned:
                            self._results_readers[h].release(slot)
                    more = [h for h, _ in pinned]
                remaining = deadline - time.monotonic()
                if out or remaining <= 0 or self._state != "running":
                    return sorted(out, key=lambda r: r.t_publish)
                ctl.wait_output(word, min(remaining, POLL_S))

    @_fenced
    def wait(
        self, frame_id: int, heads: list[str] | None = None, timeout: float = 5.0, copy: bool = True
    ) -> dict[str, Result]:
        """The outputs of ``heads`` (default: all) for frame ``frame_id``, waiting up to ``timeout`` s.

        Heads that give no output for the frame are left out of the dict, and the wait for them ends as soon as
        they know it (Note [Answered frames] in runtime/worker.py): a rate limit held it back (the foundation
        model's or the head's), it took a newer frame, it is paused or failed, its run raised, or its output was
        already overwritten. Raises TimeoutError naming the heads still pending at the timeout. A result
        published while its device work still runs (Note [Result hand-off]) is waited for in the driver when its
        head's recent results say it will be done in time, and otherwise left for its head to report done; so a
        wait outlasts ``timeout`` only by how much a result is late on that prediction. ``copy=False``: results are
        borrowed, not copied, while a lease is free (Note [Borrowed results]).
        """
        self._require_running()
        timeout = checks.timeout(timeout)
        ctl = self._res.control
        assert ctl is not None
        origin = self._origins.get(int(frame_id))
        if origin is None:
            raise ValueError(
                f"frame id {frame_id} was not submitted (or is older than the last {_ORIGINS_KEPT})"
            )
        pending = [self._head(h) for h in heads] if heads else list(self.plan.heads)
        done: dict[str, Result] = {}
        deadline = time.monotonic() + timeout
        while True:
            word = ctl.output_word()
            # Note [Answered frames]: read before looking for outputs; a frame the foundation held back reaches no head
            f_decided = ctl.get("foundation", "decided")  # before last_run, which decide() stores first
            f_ran = ctl.get("foundation", "last_run") >= origin
            held_back = not f_ran and (f_decided >= origin or ctl.rate("foundation") == 0)
            with self._read_lock:
                self._leases.drain()
                found: list[tuple[str, SlotInfo]] = []
                try:
                    for h in list(pending):
                        answered = held_back or ctl.get(h, "decided") >= origin
                        reader = self._peek_readers[h]
                        slot, newest = reader.pin_origin(origin)
                        events = self._handoffs.results.get(h)
                        if slot is not None and events is not None and events.done_after(slot, deadline):
                            # Note [Result hand-off]: its queued work is not expected to be done in time; leave
                            # it until its head says it is done (or the timeout), rather than wait past it
                            reader.release(slot)
                            continue
                        if slot is not None:
                            found.append((h, slot))
                        if (
                            slot is not None
                            or answered
                            or newest > origin
                            or ctl.state(h) in NOT_SERVING
                            or ctl.rate(h) == 0  # paused: answers nothing (one already running still may)
                        ):
                            pending.remove(h)
                    done.update(self._copy_out(found, copy))
                finally:
                    for h, slot in found:
                        self._peek_readers[h].release(slot)
            remaining = deadline - time.monotonic()
            if not pending:
                return done
            if remaining <= 0:
                raise TimeoutError(
                    f"frame {frame_id}: no output from {pending} within {timeout} s (got {sorted(done)})"
                )
            if self._state != "running":
                raise EngineDeadError("engine stopped while waiting")
            ctl.wait_output(word, min(remaining, POLL_S))

    def predict(self, image: Any, timeout: float = 30.0, timestamp: float | None = None) -> dict[str, Result]:
        """One frame through every head: ``submit`` then ``wait``; each result carries the frame (``image``) for
        ``Result.plot()``, and its outputs are in the frame's pixel grid, whatever its size. A head whose rate
        limit holds the frame back (on ``timestamp``, default now) is left out, as with ``wait``."""
        fid = self.submit(image, timestamp=timestamp)
        results = self.wait(fid, timeout=timeout)
        frame = self.boundary.check(image)
        for r in results.values():
            r.image = frame
        return results

    # ------------------------------------------------------------------------------------------ control
    @_fenced
    def set_rate(self, model: str, hz: float | None) -> None:
        """Change a model's rate limit at run time (``"foundation"`` or a head name). None: unlimited; 0: pause."""
        ctl = self._model_control(model)
        ctl.set_rate(model, checks.rate(model, hz))
        inline = self._handoffs.inline
        if inline is not None and model == "foundation":
            inline.wake()  # an armed foundation worker disarms and applies the rate first (Note [Inline launch])

    @_fenced
    def rate(self, model: str) -> float | None:
        """A model's rate limit now, as ``set_rate`` or the config set it: None unlimited, 0 paused. Cheap (one
        read of shared memory), unlike ``stats()``; for a loop that checks it every frame."""
        ctl = self._model_control(model)
        return ctl.rate(model)

    def _model_control(self, model: str) -> ControlBlock:
        """The running engine's control block, once ``model`` is known to be one of its models."""
        self._require_running()
        ctl = self._res.control
        assert ctl is not None
        if model not in ctl.index:
            raise KeyError(f"no model named {model!r}; models: {list(ctl.names)}")
        return ctl

    def stats(self) -> dict[str, Any]:
        """Counters, rates, latencies and mailbox states, read from shared memory (no logs parsed)."""
        if self._state != "running" or not self._res.fence.enter():
            return {"engine": {"state": self._state}}
        try:  # Note [Unmapping at stop]
            return self._stats()
        finally:
            self._res.fence.leave()

    def _stats(self) -> dict[str, Any]:
        ctl = self._res.control
        rings = self._res.rings
        assert ctl is not None
        models = {}
        for name in ctl.names:
            snap = ctl.snapshot(name)
            ring = rings["input"] if name == "foundation" else rings["features"]
            r = ring.stats()["readers"][name]  # type: ignore[index]
            snap["frames_seen"] = r["reads"] + r["missed"]
            snap["pending"] = r["pending"]
            models[name] = snap
        results = {}
        for h in self.plan.heads:
            st = rings[f"out.{h}"].stats()
            rr = st["readers"]["results"]  # type: ignore[index]
            results[h] = {
                "published": st["published"],
                "delivered": rr["reads"],
                "missed": rr["missed"],
                "pending": rr["pending"],
                "dropped_newest": st["dropped_newest"],
                "streaming": rr["active"],
                "borrowed": self._leases.held(h),
            }
        return {
            "engine": {
                "state": self._state,
                "mode": self.config.mode,
                "device": self.config.device,
                "uptime_s": time.monotonic() - self._t_start,
                "submitted": self._submitted,
                "rejected": self._rejected,
                # Note [Inline launch]: frames whose foundation work the submitting thread queued
                "launched_by_submit": self._handoffs.inline.launches if self._handoffs.inline else 0,
                "mps": {
                    "setting": self.config.mps,
                    "daemon": self._mps_dir,
                    "workers_on_mps": [n for n, m in models.items() if m["mps"]],
                },
            },
            "models": models,
            "results": results,
            "mailboxes": {n: r.stats() for n, r in rings.items()},
            "memory": self.memory_report,
        }

    def head_info(self, head: str) -> dict[str, Any]:
        """Output specs and metadata (labels, capacity, backbone it was trained on) of a head."""
        model = self.plan.heads[self._head(head)]
        return {"outputs": {k: str(v) for k, v in model.output_spec.items()}, **model.meta}
