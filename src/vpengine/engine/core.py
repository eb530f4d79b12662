"""The public face: ``Engine(config)``.

::

    with Engine("configs/tiny.yaml") as engine:        # plans, allocates every buffer, starts every worker
        fid = engine.submit(frame)                      # -> frame id; bad frames raise ValueError
        out = engine.wait(fid, timeout=1.0)             # {head: Result} for that frame
        engine.set_rate("depth", 5)                     # Hz, at run time; 0 pauses
        engine.set_priority("depth", 10)                # under overload the other heads give way first
        print(engine.stats()["models"]["depth"])        # counters, achieved Hz, latencies

Every result names its head, frame id, capture time and latency. Nothing is lost silently: frames a model never saw
are counted as skipped, results nobody collected as missed, and ``stats()`` shows both.

Note [Frame slots]
~~~~~~~~~~~~~~~~~~
``submit`` copies the caller's frame into an input slot: 6 MB for a 1080p frame, about 1.5 ms of memcpy, which on a
fast GPU is as long as the backbone. ``frame_slot`` lends the slot itself instead, so a camera or decoder writes the
frame there once (``cv2.VideoCapture.read(image=...)``, a driver's DMA buffer copy, a message's payload). The slot is
the writer's (state WRITING) until the with-block ends, so no reader sees a half-written frame; leaving the block
publishes it exactly as ``submit`` would (same frame ids, counters and skip accounting), and an exception or
``cancel()`` gives it back unpublished.

Note [Frames of several cameras at once]
~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~
A batch takes the frames of every camera that reach the backbone within its window, so what matters with several
cameras is how far apart a tick's frames arrive. Filling a slot (``submit``'s copy, a ``frame_slot`` block) is most of
a submit and is DRAM-bound (about 1.5 ms for a 1080p frame on an H200's host): eight cameras handed in one after the
other took 12 ms, past the window, and the batch split. So a slot is filled outside the submit lock, under its camera's
own lock: cameras' threads fill their slots at once, one frame of a camera at a time. Only taking a slot and
publishing it hold the submit lock, so frames still enter the ring in one order (frame ids, placements and the inline
launch keep their single writer), and the input ring holds a slot a camera more for the frames being filled (3 a
camera: its reader's, its newest, the one being filled). A thread with a ``frame_slot`` block open may not submit
(its camera's lock is held: the same camera would deadlock), and buffers lent for frames of another size are one
per camera and size, so two cameras' blocks never share one.
"""

from __future__ import annotations

import collections
import functools
import logging
import numbers
import os
import shutil
import threading
import time
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np
import torch

from vpengine import checks
from vpengine.config import EngineConfig, HeadConfig, load_config
from vpengine.engine import heads
from vpengine.engine.boundary import Boundary, Placement, buffer_for
from vpengine.engine.heads import head_spec
from vpengine.engine.intake import FrameSlot
from vpengine.engine.results import Outbox, Result
from vpengine.engine.stats import engine_stats, memory_report
from vpengine.models.preprocess import IMAGENET_MEAN
from vpengine.models.weights import check_checkpoints
from vpengine.runtime.control import ControlBlock
from vpengine.runtime.fence import MappingFence
from vpengine.runtime.governor import Governor
from vpengine.runtime.gpu import CudaSetup, prepare_cuda, worker_env
from vpengine.runtime.handoff import Handoffs
from vpengine.runtime.lanes import Lanes
from vpengine.runtime.plan import Plan, check_preallocation, mailboxes, make_plan
from vpengine.runtime.supervisor import EngineDeadError, EngineStartError, Runner, close_log_file, log_to_file
from vpengine.runtime.worker import WorkerSpec
from vpengine.transport.ring import SlotInfo, SlotRing

log = logging.getLogger("vpengine")

__all__ = ["Engine", "EngineDeadError", "EngineStartError", "FrameSlot", "Result"]  # FrameSlot, Result: re-exported

_ORIGINS_KEPT = 8192


_F = TypeVar("_F", bound=Callable[..., Any])


def _fenced(method: _F) -> _F:
    """An API method that runs inside the engine's fence: what it touches stays mapped until it returns, and once
    ``stop()`` has begun it raises EngineDeadError (Note [Unmapping at stop] in runtime/fence.py)."""

    @functools.wraps(method)
    def call(self: Engine, *args: Any, **kw: Any) -> Any:
        with self._res.fence:
            return method(self, *args, **kw)

    return cast(_F, call)


def _env_for(setup: CudaSetup | None, cfg: EngineConfig, name: str) -> dict[str, str]:
    return worker_env(cfg, setup, name)


class _Resources:
    """What must be released even if the user forgets stop(): workers, mailboxes, control block. Refers to nothing
    that refers to the Engine, so that an Engine nobody refers to is collected and this is closed by its finalizer."""

    def __init__(self) -> None:
        self.runner: Runner | None = None
        self.governor: Governor | None = None  # Note [Give way] in runtime/governor.py
        self.rings: dict[str, SlotRing] = {}
        self.control: ControlBlock | None = None
        self.dirs: list[str] = []  # private temporary directories (e.g. the no-MPS pipe directory)
        self.fence = MappingFence()  # Note [Unmapping at stop]
        self.log_file: logging.Handler | None = None
        self.owner = os.getpid()

    def close(self) -> list[str]:
        forced: list[str] = []
        if self.governor is not None:  # first: it reads the control block
            self.governor.stop()
            self.governor = None
        if os.getpid() != self.owner:
            # A process forked from the engine's (Note [Child lifecycle]), its finalizer run at its exit: the
            # workers, the control block and the directories are the engine's; only drop the references.
            self.runner, self.dirs = None, []
        if self.runner is not None:
            forced = self.runner.stop()
            for thread in self.runner.threads_alive():  # abandoned workers: unmap once they are gone
                self.fence.hold_until_gone(thread)
            self.runner = None
        if self.log_file is not None:
            close_log_file(self.log_file)
            self.log_file = None
        for d in self.dirs:
            shutil.rmtree(d, ignore_errors=True)
        self.dirs = []
        self.fence.close(self._unmap)  # Note [Unmapping at stop]: now, or once the last user is gone
        return forced

    def _unmap(self) -> None:
        for ring in list(self.rings.values()):  # a head added or removed meanwhile changes the dict
            ring.close()
        self.rings = {}
        if self.control is not None:
            self.control.close()
            self.control = None


def _say_half_precision_on_cpu(cfg: EngineConfig) -> None:
    """A warning for fp16 models on a CPU: PyTorch's CPU kernels are float32's, and a ViT in fp16 there takes
    seconds a frame (the shipped GPU config run with --device cpu does). ONNX models say it themselves."""
    if torch.device(cfg.device).type != "cpu":
        return
    models = [(name, cfg.model(name)) for name in cfg.model_names()]
    half = [name for name, m in models if (m.precision or cfg.precision) == "fp16" and m.backend != "onnx"]
    if half:
        log.warning(
            "%s run in fp16 on the CPU, which PyTorch does slowly (float32 is the CPU's); precision: fp32 (or "
            "--set precision=fp32) for a CPU run",
            ", ".join(half),
        )


def _say_what_will_not_run(cfg: EngineConfig) -> None:
    """Warnings for a config that starts with nothing coming out: no heads (an empty file, heads: []), or a paused
    foundation model (rate_hz: 0), which every head waits for. Legal (heads are added, rates set at run time), but
    a run of such a config otherwise ends with zeros and no word why. And for process groups in thread mode, which
    mean nothing there."""
    if not cfg.heads:
        log.warning("the config has no heads: the foundation model runs on each frame and no result comes out")
    grouped = [name for name in cfg.model_names() if cfg.model(name).process]
    if cfg.mode == "thread" and grouped:
        log.warning(
            "%s: process is for process mode; in thread mode every model shares this process already",
            ", ".join(grouped),
        )
    if cfg.foundation_model.rate_hz == 0:
        log.warning(
            "foundation_model.rate_hz is 0: the engine starts paused, and no frame runs until "
            "set_rate('foundation', ...) raises it"
        )


class Engine:
    """One foundation model shared by many heads. See the module docstring for a tour."""

    def __init__(
        self,
        config: EngineConfig | str | Path | dict[str, Any] | None = None,
        overrides: list[str] | None = None,
    ) -> None:
        self.config = load_config(config, overrides)
        self.plan: Plan = make_plan(self.config)
        check_checkpoints(self.config, {"foundation": self.plan.foundation, **self.plan.heads})  # before any worker
        _say_half_precision_on_cpu(self.config)
        _say_what_will_not_run(self.config)
        self._res = _Resources()
        self._finalizer = weakref.finalize(self, _Resources.close, self._res)
        self._state = "planned"
        # Note [Frames of several cameras at once]: taking and publishing an input slot; filling one, by camera
        self._submit_lock = threading.Lock()
        self._filling_locks = [threading.Lock() for _ in range(max(1, len(self.config.cameras)))]
        self._filling: set[int] = set()  # threads holding an open frame_slot (and their camera's filling lock)
        self._next_id = 0
        self._submitted = 0
        self._rejected = 0
        # frame id -> (its input seq, its camera's index)
        self._origins: collections.OrderedDict[int, tuple[int, int]] = collections.OrderedDict()
        # input seq -> where the frame lies in the input canvas (Note [Frame grid] in boundary.py)
        self._placements: collections.OrderedDict[int, Placement] = collections.OrderedDict()
        self.boundary = Boundary(
            self.config,
            {h: (m.meta, m.output_spec) for h, m in self.plan.heads.items()},
            self.plan.foundation.meta.get("normalize_mean", IMAGENET_MEAN),
        )
        self._staged: list[dict[tuple[int, int], np.ndarray]] = [{} for _ in self._filling_locks]  # by camera
        self._t_start = 0.0
        self.memory_report: dict[str, Any] = {}
        self._cuda: CudaSetup | None = None  # set at start on CUDA
        self._handoffs = Handoffs()  # thread mode: replaced at start (runtime/handoff.py)
        self._seats: dict[str, str] = {}  # head added at run time -> its seat (Note [Heads at run time])
        self._heads_lock = threading.Lock()  # one add_head or remove_head at a time

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
                self._cuda = prepare_cuda(cfg)
                res.dirs.append(self._cuda.nomps_dir)
            boxes = mailboxes(plan, shared)
            check_preallocation(boxes)  # before any of it is allocated
            for m in boxes:
                res.rings[m["name"]] = SlotRing.create(**m)
            if cfg.logging.file:
                res.log_file = log_to_file(cfg.logging.file, cfg.logging.level, "engine")
            res.control = ControlBlock.create(self.lanes.control_names())
            for lanes in self.lanes.by_model.values():
                for lane in lanes:  # Note [Cameras]: a rate per camera
                    res.control.set_rate(lane.entry, lane.rate_hz)
            res.governor = Governor(res.control, cfg, self.lanes)
            specs = self._worker_specs()
            if shared:
                from vpengine.runtime.process import ProcessRunner

                # not a bound method: the runner must not refer to the Engine (see _Resources)
                env_for = functools.partial(_env_for, self._cuda)
                res.runner = ProcessRunner(specs, res.rings, res.control, cfg, env_for=env_for)
            else:
                from vpengine.runtime.handoff import make_handoffs
                from vpengine.runtime.threads import ThreadRunner

                self._handoffs = make_handoffs(res.rings, heads, device.type == "cuda")
                res.runner = ThreadRunner(specs, res.rings, res.control, cfg, handoffs=self._handoffs)
            res.runner.start()
            res.governor.start()
        except BaseException:
            self._state = "stopped"
            res.close()
            raise
        self._input_writer = res.rings["input"].writer()
        self._frame_views = [v["frame"].numpy() for v in res.rings["input"].views]
        assert res.control is not None
        self._outbox = Outbox(
            res.rings,
            plan.heads,
            res.control,
            self._handoffs,
            self.boundary,
            self._placements,
            self.lanes,
        )
        self._t_start = time.monotonic()
        self._state = "running"
        self.memory_report = memory_report(res.rings, res.control, device)
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
                lanes=plan.lanes.of("foundation"),
                in_ring=rings["input"].desc,
                out_ring=rings["features"].desc,
                notify_output=False,
            )
        ]
        return specs + [head_spec(plan, rings, name, dump) for name in plan.heads]

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
                f"engine is {self._state}; call start() first" if self._state == "planned" else "engine is stopped"
            )
        ctl = self._res.control
        if ctl is not None and ctl.state("foundation") == "failed":
            raise EngineDeadError(f"the foundation model has failed for good: {ctl.last_error('foundation')}")

    # -------------------------------------------------------------------------------------------- input
    @_fenced
    def submit(
        self, frame: Any, frame_id: int | None = None, timestamp: float | None = None, camera: str | None = None
    ) -> int:
        """Hand a frame to the engine. Returns its frame id (``frame_id`` or the next integer).

        ``frame``: HxWx3 of the input dtype and colour order, of any size up to ``input.max_frame_side``; every
        output for it comes back in its pixel grid (Note [Frame grid] in boundary.py). ``timestamp`` is the capture
        time in seconds (e.g. the camera's stamp; default: now): rate limits run on these stamps, so a file's frames
        stamped by their position obey them however fast they are fed. Never blocks on the models: if the
        foundation model is busy, the newest frame wins and the overwritten one is counted as skipped. ``camera``:
        which of the configured cameras it comes from (Note [Cameras] in runtime/worker.py; None: the only one);
        submit each camera's frames from a thread of its own, so that a tick's frames arrive together and run as
        one batch (Note [Frames of several cameras at once]). Raises ValueError naming what was expected if the
        frame is not an image.
        """
        self._require_running()
        try:
            cam = self._camera(camera)
            arr = self.boundary.check(frame)
            frame_id, timestamp = checks.frame_id(frame_id), checks.timestamp(timestamp)
        except ValueError:
            self._rejected += 1
            raise
        t_submit = time.monotonic()
        t_capture = time.time() if timestamp is None else float(timestamp)
        self._refuse_inside_frame_slot()
        with self._filling_locks[cam]:  # Note [Frames of several cameras at once]
            slot = self._acquire_input()
            return self._enter_frame(
                slot, lambda view: self.boundary.write(arr, view), frame_id, t_capture, t_submit, cam
            )

    @_fenced
    def frame_slot(
        self,
        frame_id: int | None = None,
        timestamp: float | None = None,
        size: tuple[int, int] | None = None,
        camera: str | None = None,
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
        size, fitted into the slot when the block ends (Note [Frame grid] in boundary.py); ``camera``: as for
        ``submit``, and its configured height and width are the default ``size``. Its content is whatever
        an earlier frame left there until you write it. Assign what a writer hands back to ``slot.array``
        (``ok, slot.array = cap.read(image=slot.array)``): a writer that allocated a new array instead of writing
        into it (OpenCV does when the sizes differ) raises ValueError naming both sizes. Leaving the block submits
        it (latency counts from there); an exception inside the block or ``cancel()`` gives the slot back and
        submits nothing. One slot of a camera is open at a time: other threads' ``submit``/``frame_slot`` calls for
        that camera wait for it to close, so fill it promptly (a camera read, a decode), while other cameras' go on
        (Note [Frames of several cameras at once]); calling them from inside the block raises RuntimeError.
        """
        self._require_running()
        self._refuse_inside_frame_slot()
        cam = self._camera(camera)
        cam_cfg = self.config.cameras[cam] if self.config.cameras else None
        if size is None and cam_cfg is not None and cam_cfg.height and cam_cfg.width:
            size = (cam_cfg.height, cam_cfg.width)
        if size is not None:
            hw = tuple(size) if isinstance(size, (tuple, list)) else ()
            whole = (  # a whole float passes: OpenCV's CAP_PROP_FRAME_HEIGHT is one
                isinstance(v, numbers.Integral) or (isinstance(v, float) and v.is_integer()) for v in hw
            )
            if len(hw) != 2 or any(isinstance(v, bool) for v in hw) or not all(whole):
                raise ValueError(f"frame_slot size must be (height, width) in whole pixels, got {size!r}")
            h, w = (int(v) for v in hw)
            if not (0 < h <= self.boundary.max_side and 0 < w <= self.boundary.max_side):
                raise ValueError(
                    f"frame_slot size {size!r}: height and width must be 1..{self.boundary.max_side} (input.max_frame_side)"
                )
            size = None if (h, w) == self.boundary.canvas_hw else (h, w)
        return FrameSlot(self, checks.frame_id(frame_id), checks.timestamp(timestamp), size, cam)

    def _camera(self, camera: str | None) -> int:
        """The index (slot tag) of ``camera``; None: the only camera. ValueError naming the cameras otherwise."""
        return self.lanes.tag(camera)

    @property
    def cameras(self) -> list[str]:
        """The cameras, in the configured order (``cameras`` in the config; one named ``camera`` without)."""
        return list(self.lanes.cameras)

    @property
    def lanes(self) -> Lanes:
        """Every (model, camera) pair: its camera's name and tag, its reader, its control-block entry (Note [Lanes]
        in runtime/lanes.py). ``engine.lanes.of("depth")``: the lanes of head ``depth``, in the configured order."""
        return self.plan.lanes

    def _staging(self, camera: int, size: tuple[int, int]) -> np.ndarray:
        """The buffer ``frame_slot(size=...)`` lends for frames of another size: one per camera and size
        (``buffer_for``), so blocks of two cameras open at once never share one."""
        return buffer_for(self._staged[camera], size, self.boundary.dtype)

    def _refuse_inside_frame_slot(self) -> None:
        if threading.get_ident() in self._filling:
            raise RuntimeError("a frame_slot is open in this thread: submit after its with-block ends")

    def _acquire_input(self) -> SlotInfo:
        """The input slot to fill next; the caller holds its camera's filling lock, so a camera fills one slot at a
        time, and the ring has a slot a camera for it (Note [Frames of several cameras at once])."""
        with self._submit_lock:
            slot = self._input_writer.acquire()
        assert slot is not None  # input ring is drop_oldest with n_slots >= readers + 2 * cameras
        return slot

    def _enter_frame(
        self,
        slot: SlotInfo,
        fill: Callable[[np.ndarray], Placement],
        frame_id: int | None,
        timestamp: float | None,
        t_submit: float,
        camera: int,
    ) -> int:
        """Check, write and publish a frame into input ``slot`` (``submit``, and a ``frame_slot`` block's end):
        ``fill`` writes it into the slot's frame array (or finds it written there) and says where it lies;
        ``timestamp`` is its capture time (None: now). Its frame id. Anything that raises gives the slot back
        unpublished: a leaked slot is a frame the ring never gets again. The caller holds its camera's filling lock:
        the slot is filled outside the submit lock, and published under it (Note [Frames of several cameras at
        once])."""
        try:
            stamp = checks.timestamp(timestamp)
            t_capture = time.time() if stamp is None else stamp
            placement = fill(self._frame_views[slot.index])
            with self._submit_lock:
                return self._publish_input(slot, frame_id, t_capture, t_submit, placement, camera)
        except BaseException:
            self._input_writer.abort(slot)
            raise

    def _publish_input(
        self,
        slot: SlotInfo,
        frame_id: int | None,
        t_capture: float,
        t_submit: float,
        placement: Placement,
        camera: int,
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
            seq = inline.publish(self._input_writer, slot, fid, t_capture, t_submit, camera)
        else:
            seq = self._input_writer.publish(slot, fid, t_capture, t_submit, tag=camera)
        self._submitted += 1
        self._origins[fid] = (seq, camera)
        if len(self._origins) > _ORIGINS_KEPT:
            self._origins.popitem(last=False)
        return fid

    @_fenced
    def latest(self, head: str, copy: bool = True, camera: str | None = None) -> Result | None:
        """The newest output of ``head``, or None if it has produced nothing yet. ``copy=False``: borrowed, not
        copied, while a lease is free (Note [Borrowed results] in results.py). ``camera``: the newest of that
        camera's frames (ValueError for a camera the head does not serve); None: of any camera's."""
        self._require_running()
        tag = None
        if camera is not None:
            self._camera(camera)
            tag = self.lanes.select(self._outbox.head(head), camera)[0].tag
        return self._outbox.latest(head, copy, tag)

    @_fenced
    def results(self, timeout: float = 0.0, heads: list[str] | None = None, copy: bool = True) -> list[Result]:
        """Every output published since the previous call, oldest first; waits up to ``timeout`` for at least one.

        The first call starts the stream (earlier outputs are not returned). Call it regularly: if it falls
        more than ``output.slots`` behind, the oldest unread outputs are overwritten and counted as missed in
        ``stats()["results"]`` (or the head waits, with ``output.overflow: block``). ``copy=False``: results are
        borrowed, not copied, while a lease is free (Note [Borrowed results] in results.py).
        """
        self._require_running()
        heads = checks.names(heads, "heads")
        return self._outbox.results(checks.timeout(timeout), heads, copy, lambda: self._state == "running")

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
        borrowed, not copied, while a lease is free (Note [Borrowed results] in results.py).
        """
        self._require_running()
        timeout, heads = checks.timeout(timeout), checks.names(heads, "heads")
        if frame_id is None:  # what a cancelled frame_slot's frame_id is
            raise ValueError("frame_id is None: no frame was submitted (a frame_slot that was cancelled has none)")
        known = self._origins.get(checks.frame_id(frame_id))  # type: ignore[arg-type]
        if known is None:
            raise ValueError(f"frame id {frame_id} was not submitted (or is older than the last {_ORIGINS_KEPT})")
        origin, camera = known
        return self._outbox.wait(origin, camera, frame_id, heads, timeout, copy, lambda: self._state == "running")

    def predict(
        self, image: Any, timeout: float = 30.0, timestamp: float | None = None, camera: str | None = None
    ) -> dict[str, Result]:
        """One frame through every head: ``submit`` then ``wait``; each result carries the frame (``image``) for
        ``Result.plot()``, and its outputs are in the frame's pixel grid, whatever its size. A head whose rate
        limit holds the frame back (on ``timestamp``, default now) is left out, as with ``wait``."""
        fid = self.submit(image, timestamp=timestamp, camera=camera)
        results = self.wait(fid, timeout=timeout)
        picture = self.boundary.picture(self.boundary.check(image))  # BGR uint8, as Result.plot draws
        for r in results.values():
            r.image = picture
        return results

    # ------------------------------------------------------------------------------------------ control
    @_fenced
    def set_rate(self, model: str, hz: float | None, camera: str | None = None) -> None:
        """Change a model's rate limit at run time (``"foundation"`` or a head name). None: unlimited; 0: pause.
        With several cameras a model has a rate per camera: ``camera`` sets one, None all of the model's."""
        ctl = self._model_control(model)
        hz = checks.rate(model, hz)
        for entry in self._entries(model, camera):
            ctl.set_rate(entry, hz)
        ctl.wake(model)
        inline = self._handoffs.inline
        if inline is not None and model == "foundation":
            inline.wake()  # an armed foundation worker disarms and applies the rate first (Note [Inline launch])

    @_fenced
    def rate(self, model: str, camera: str | None = None) -> float | None:
        """A model's rate limit now, as ``set_rate`` or the config set it: None unlimited, 0 paused. One read of
        shared memory. ``camera``: whose, with several (None: the first the model serves)."""
        return self._model_control(model).target(self._entries(model, camera)[0])

    @_fenced
    def recent_runs(self, model: str, camera: str | None = None, since: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """When ``model``'s recent runs started (``time.monotonic()``, in order) and their end-to-end latencies in
        seconds (frame submitted to output done; a run whose device work is still going shows the time so far),
        for runs started at ``since`` or later: the last 512 runs of each camera's lane at most, as the engine
        recorded them, for a window of your own (``stats()`` sums up the last ones). ``camera``: that camera's runs
        (None: every camera's; a batch of several cameras' frames is a run of each)."""
        ctl = self._model_control(model)
        runs = [ctl.recent_runs(entry, since) for entry in self._entries(model, camera)]
        starts, e2e = np.concatenate([s for s, _ in runs]), np.concatenate([e for _, e in runs])
        order = np.argsort(starts, kind="stable")
        return starts[order], e2e[order]

    @_fenced
    def set_priority(self, head: str | None, priority: int, camera: str | None = None) -> None:
        """Change a head's priority now (higher: more important, checks.MIN_PRIORITY to MAX_PRIORITY): lower lanes
        give way when the device cannot serve every rate (Note [Give way] in runtime/governor.py). ``camera``: that
        camera's lane only; ``head=None`` with a ``camera``: the camera's priority. KeyError for an unknown head,
        ValueError for a bad priority or camera; on an error nothing changes."""
        self._require_running()
        governor = self._res.governor  # None once stop() has begun; the fence keeps the control block mapped
        if governor is None:
            raise EngineDeadError("engine is stopped")
        governor.set_priority(head, priority, camera)

    @_fenced
    def add_head(self, head: HeadConfig | dict[str, Any] | str) -> str:
        """Build, warm up and attach a head while the backbone and the other heads keep serving; returns its name.
        ``head``: its config, as under ``heads:`` in a config file (a dict, YAML text or a HeadConfig), validated
        like the file. It takes one of ``runtime.spare_heads`` seats (Note [Heads at run time] in runtime/lanes.py).
        ConfigError for a bad config or a name taken, EngineStartError if it fails to build or warm up; on any error
        the engine is as it was."""
        return heads.add_head(self, head)

    @_fenced
    def remove_head(self, name: str) -> None:
        """Stop and detach head ``name``, and free its worker, model and output mailbox; its seat is free for another
        (a head of the config leaves no seat). KeyError for an unknown head, ValueError for the foundation model or
        the last head; on an error nothing changes."""
        heads.remove_head(self, name)

    def _entries(self, model: str, camera: str | None) -> list[str]:
        """The control-block entries holding ``model``'s rate for ``camera`` (None: all its cameras)."""
        return [lane.entry for lane in self.lanes.select(model, camera)]

    def _model_control(self, model: str) -> ControlBlock:
        """The running engine's control block, once ``model`` is known to be one of its models."""
        self._require_running()
        ctl = self._res.control
        assert ctl is not None
        if model not in self.lanes.by_model:  # the control block also holds the spare seats' entries
            raise KeyError(f"no model named {model!r}; models: {list(self.lanes.by_model)}")
        return ctl

    def stats(self) -> dict[str, Any]:
        """Counters, rates, latencies and mailbox states, read from shared memory (no logs parsed)."""
        if self._state != "running" or not self._res.fence.enter():
            return {"engine": {"state": self._state}}
        try:  # Note [Unmapping at stop]
            return engine_stats(self)
        finally:
            self._res.fence.leave()

    def head_info(self, head: str) -> dict[str, Any]:
        """Output specs and metadata (labels, capacity, backbone it was trained on) of a head."""
        if head not in self.plan.heads:
            raise KeyError(f"no head named {head!r}; heads: {list(self.plan.heads)}")
        model = self.plan.heads[head]
        return {"outputs": {k: str(v) for k, v in model.output_spec.items()}, **model.meta}
