"""The one worker loop, used for the foundation model and every head, in a thread or in a child process.

``WorkerCore`` holds the logic and no IPC (it is handed rings and a control block that are already mapped), so the
same object runs in-process under tests and debuggers, in a thread (thread mode), or inside a spawned child
(process mode, ``process.py``). One loop for one camera or several: it runs over the model's lanes (Note [Lanes] in
lanes.py), and one camera's frame is a batch of one. One iteration::

    rate gates -> pin newest inputs (with timeout) -> acquire output slots -> stage inputs on the device
      -> model -> copy outputs into the slots -> device sync -> publish outputs -> release inputs -> counters

An executor bound to the slots (Note [Slot-bound runs], compiled models on CUDA) does the staging, the model and the
copy into the output slot itself, from graphs captured at start.

Note [Answered frames]
~~~~~~~~~~~~~~~~~~~~~~
``Engine.wait(frame)`` must learn that a model will give no output for a frame as soon as the model knows it, or a
caller waiting for every head (``vpengine run``'s lockstep pacing, ``Engine.predict``) waits out a rate-limited
head's whole period on every frame. So every worker answers each frame it is done with: after publishing its output,
or at once when its rate gate holds the frame back, a run of it fails or finds no output slot, it records the frame's
input seq (its origin) in the control block (``ControlBlock.decide``: ``decided``, and ``last_run`` when it
published), and wakes the engine's waiters. A worker takes frames in order, so every frame up to ``decided`` is
answered: ``wait`` reads ``decided`` before it looks for the output in the ring, and finding none then means none is
coming. A frame the foundation model held back reaches no head: ``wait`` sees that as the foundation's ``decided``
at or past the frame with its ``last_run`` before it. Frames a model missed because it was busy (newest wins) are
answered by the newer frame it took.

Note [Cameras]
~~~~~~~~~~~~~~
Several cameras feed one engine: one backbone's weights, one set of workers and mailboxes. Every frame is tagged
with its camera (Note [Tagged slots] in transport/ring.py) and a model keeps one *lane* per camera it serves: that
camera's reader of its input ring, its rate gate, and its control-block entry (``model@camera``: rate, counters,
latencies, answered frames), so rates, counts and Note [Answered frames] hold per camera. A model takes its lanes'
frames as one batch (``_take_ring``): it waits for the first frame of any camera, then at most
``runtime.batch_window_ms`` for the other cameras whose next frame is due by then; a camera whose frame comes later
goes in the next batch, counted ``late``. A camera's next frame is due one interval after its last, the interval
being the median of its last ``SPACINGS`` frame spacings (the lower middle one of an even count), not a moving
average: one long gap (a paused stream, a warm-up of frames one at a time) kept the average far above the camera's
rate for a dozen frames or more, through which the camera was not waited for and a tick's frames ran in two or three
batches, costing more device time a frame than one batch; the median has a new rate after three frames and ignores
one gap or burst. A camera that has sent nothing for three spacings is not waited for; there the longer of the
median and a moving average counts, or a camera handed in at its caller's pace, whose spacing varies several-fold,
looked stopped after one longer spacing. The frames the gates admit (several: copied into preallocated batch buffers
of one frame per lane; one: its slot, viewed) run as one batch through the model (Note [Batched models] in
models/base.py; a compiled model has a graph for every batch size up to its lanes; ``stats()``' ``runs`` /
``batches`` is the mean batch), and each frame's outputs are copied into its own slot and published with its
camera's tag. When the model cannot keep up (its batches took longer, on average, than the cameras' frames come:
here a moving average of each camera's spacing, smoother than the median), the least important lane by priorities as
they are now (runtime/priority.py; among equals the camera last in the configured order) leaves its frame for the
next batch, counted ``deferred`` (never twice in a row, so no camera starves). The deferred frame stays pinned and
unanswered, and runs in the next batch unless a newer frame of its camera is there by then and the model reads the
newest (the deferred one is then skipped and answered; a fifo model runs it first). A deferral is a guess from
wall-clock averages and may be wrong (one slow batch under load is enough), so it must never cost a frame on its
own: a caller that waits for every frame (lockstep pacing) gets every output, a batch later.
With one lane there is no window to wait and no frame to defer: each frame is a batch of one, which the foundation
may also take from the submitting thread (Note [Inline launch]).

Note [Frame errors]
~~~~~~~~~~~~~~~~~~~
A model that raises on a frame fails that frame, not the worker: as a server answers a request that failed and keeps
its model loaded, the worker answers the run's frames (Note [Answered frames]; no output, so ``Engine.wait`` returns
without it), counts the error in its model's ``errors``, keeps the text in ``last_error``, logs it once per reason
(exception type and where it was raised), and takes the next frame. Restarting it instead took a head out for
seconds per raise, and one raising on one frame in a hundred was failed for good. Only what leaves the worker unable
to go on is raised out of the loop, to its runner, which restarts it under ``runtime.max_restarts`` (``poisons``):
anything not an ``Exception`` (KeyboardInterrupt, SystemExit), and CUDA errors (``torch.AcceleratorError``, or a
RuntimeError saying "CUDA error"), after which the process's CUDA context is unusable (sticky errors) and only a
fresh process recovers; likewise a failure after the run's work was queued (waiting for the device, publishing).
Dead and hung workers are found by their runner as before.

Note [One call for a batch's copies]
~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~
A batch's frames go into the model's batch buffers in one call, and its outputs into their slots in another
(``torch._foreach_copy_``), not in a copy (or a stack) a frame and key: a tensor op called from Python gives up the
interpreter lock and takes it back, and in thread mode, where every model and the callers' threads share one
interpreter, each take-back may wait its turn. The backbone's 8 feature tensors for 8 cameras were 64 output copies
a batch, and each head stacked every feature key it reads. On the CPU with models that cost nothing
(``benchmarks/engine_overhead.py``) the engine goes faster for it (docs/benchmarks.md). Copies between the host and
the device (host input slots, a head's outputs kept on the host) stay one a tensor: one call over two devices would
copy each pair in turn anyway.

Note [First batch]
~~~~~~~~~~~~~~~~~~
Invariant: a served frame runs no kernel for the first time. The executor's warm-up runs the model alone; the
worker's own copies around it (a batch's frames into its batch buffers, its outputs into their slots: Note [One call
for a batch's copies]) first ran on the first batch of several cameras a stream sent, and a kernel's first launch
loads its module (CUDA loads lazily): host memory the driver maps and fills while the worker's thread waits. On an
H200 with 8 cameras that was some 4,000 page faults in the foundation's thread within the stream's first half second,
in a batch's output copies (none in the model's call or the input copies), and the slowest ticks of a 5 s stream
were its first ones (docs/benchmarks.md). So on CUDA a worker runs one batch of a frame per lane through the same
code before READY (``warm_batch``), into output slots it acquires and gives back unpublished, which no reader sees.
The batch is the largest: a model whose sizes are not all captured (eager, ONNX) may still run a smaller size the
first time on a served frame. Not on the CPU, where there is nothing to load and a batch of a large model costs
seconds of start; not where the output ring was published to before (as a restarted worker's usually was), whose
slots readers may hold (a borrowed result): there the first batch is not warmed. A head added at run time has a new
mailbox and warms its batch like the others.

The hand-offs that thread mode on CUDA uses between models (events instead of host waits, the submitting thread
launching the foundation's work) live in handoff.py.
"""

from __future__ import annotations

import collections
import logging
import math
import os
import statistics
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from vpengine.backends.base import tensor_bytes
from vpengine.config import EngineConfig, RuntimeConfig, load_config
from vpengine.models.base import ModelBuildError, Role, check_outputs, random_inputs
from vpengine.runtime.control import PAUSED, POLL_S, RUNNING, ControlBlock, ControlDesc
from vpengine.runtime.device import RESTREAM_S, DeviceContext
from vpengine.runtime.handoff import WorkerHandoff
from vpengine.runtime.lanes import Lane
from vpengine.runtime.priority import least_important
from vpengine.runtime.rate import RateGate
from vpengine.specs import SpecDict
from vpengine.transport.ring import RingDesc, RingReader, SlotInfo, SlotRing

log = logging.getLogger("vpengine.worker")


@dataclass(frozen=True, kw_only=True)
class WorkerSpec:
    """Everything a worker needs, picklable so it can cross into a spawned child."""

    name: str
    role: Role
    config: dict[str, Any]  # EngineConfig.model_dump(mode="json")
    upstream: SpecDict
    upstream_meta: dict[str, Any]
    lanes: tuple[Lane, ...]  # the cameras it serves, in the configured order (Note [Lanes] in lanes.py)
    in_ring: RingDesc
    out_ring: RingDesc
    notify_output: bool
    control: ControlDesc | None = None

    def engine_config(self) -> EngineConfig:
        return load_config(self.config)


#: runtime.batch_window_ms's default, in seconds
_DEFAULT_WINDOW_S = RuntimeConfig.model_fields["batch_window_ms"].default * 1e-3
#: A lane's frame interval is the median of its last this many frame spacings (Note [Cameras])
SPACINGS = 5


@dataclass
class _Lane:
    """A lane's state in its worker (Note [Cameras])."""

    lane: Lane
    reader: RingReader
    gate: RateGate
    last_arrival: float = -math.inf  # when its last frame reached the engine (monotonic)
    interval: float = 0.0  # when its next frame is due after its last: median of its last spacings (0: not known)
    spacings: collections.deque[float] = field(default_factory=lambda: collections.deque(maxlen=SPACINGS))
    mean_interval: float = 0.0  # moving average of its spacing: for deferral, and whether it still delivers

    @property
    def tag(self) -> int:
        return self.lane.tag

    @property
    def entry(self) -> str:
        return self.lane.entry

    def arrived(self, t: float) -> None:
        if self.last_arrival > -math.inf and t > self.last_arrival:
            step = t - self.last_arrival
            self.spacings.append(step)
            self.interval = statistics.median_low(self.spacings)  # of two or four: the lower, not a gap's mean
            m = self.mean_interval
            self.mean_interval = step if m <= 0 else m + 0.125 * (step - m)
        self.last_arrival = t

    def due_by(self, deadline: float, now: float) -> bool:
        """Whether its next frame should come by ``deadline``: it delivers frames, and the next is due then."""
        if self.interval <= 0:
            return False
        # still delivering: judged by the longer of its two spacings, or a caller-paced camera, whose spacing varies
        # several-fold, looks stopped after one long spacing
        live = now - self.last_arrival < 3 * max(self.interval, self.mean_interval)
        return live and self.last_arrival + self.interval <= deadline


class WorkerCore:
    """The loop of one model over its lanes. Construct with mapped rings; ``run`` until ``should_stop`` says so."""

    def __init__(
        self,
        spec: WorkerSpec,
        model: Callable[[dict[str, torch.Tensor]], dict[str, torch.Tensor]],
        output_spec: SpecDict,
        in_ring: SlotRing,
        out_ring: SlotRing,
        control: ControlBlock,
        device: DeviceContext,
        poll_s: float = POLL_S,
        bound: bool = False,
        handoff: WorkerHandoff | None = None,
    ) -> None:
        self.spec = spec
        self.name = spec.name
        self.model = model
        self.output_spec = output_spec
        # Note [Cameras]: one lane per camera this model serves (Note [Lanes] in lanes.py), in the configured order
        self.lanes = [_Lane(lane, in_ring.reader(lane.reader), RateGate()) for lane in spec.lanes]
        self._by_tag = {lane.tag: lane for lane in self.lanes}
        cfg = spec.engine_config()
        self.window = cfg.runtime.batch_window_ms * 1e-3
        # Note [Cameras]: a deferred frame gives way to a newer one of its camera only where newest wins; a fifo
        # model runs every frame
        self._newest_wins = cfg.model(spec.name).input_mode == "latest"
        self.writer = out_ring.writer()
        self.control = control
        self.dev = device
        self._restream_at = 0.0  # Note [Stream priority at run time] in device.py
        self.poll_s = poll_s
        self._checked: set[int] = set()  # batch sizes whose outputs were checked against the model's spec
        self._reasons: set[tuple[str, str, int]] = set()  # errors logged (Note [Frame errors])
        self._should_stop: Callable[[], bool] = lambda: False
        self._keys = input_keys(spec, in_ring)
        self._in_ring = in_ring
        handoff = handoff or WorkerHandoff()
        # Notes [Event hand-off], [Result hand-off] in handoff.py: this worker waits on the device for the events of
        # its input slots, and publishes queued work with the events of its output slots.
        self._in_events = handoff.in_events
        self._out_events = handoff.out_events
        # Note [Inline launch]: the submitting thread may queue this (foundation) worker's work, one frame at a
        # time: with several cameras the frames wait for their batch instead
        self._inline = handoff.inline if len(self.lanes) == 1 else None
        self._thread: int | None = None  # the thread running the loop (Note [Launch path] in handoff.py)
        self._spare: SlotInfo | None = None  # the output slot an armed worker offers
        self._batch_s = 0.0  # moving average of how long a batch takes (Note [Cameras])
        self._held: dict[int, SlotInfo] = {}  # lane tag -> its deferred frame, pinned, admitted (Note [Cameras])
        self._deferred_tag: int | None = None  # the lane whose frame was deferred last (Note [Cameras])
        # the foundation, which every camera's frames pass, says once if the window reaches a camera's next frame
        self._window_said = spec.role != "foundation" or len(self.lanes) < 2 or self.window <= 0
        # The executor runs straight from the slots (Note [Slot-bound runs]): no staging, no copies here.
        self._bound = bound
        # A batch of one frame is its slot, viewed, where the model's device holds the input ring. Otherwise the
        # frames are copied into preallocated buffers of one frame per lane (Note [Cameras]).
        self._direct = in_ring.data_region.device == device.device
        self._copies: dict[str, torch.Tensor] | None = None
        if len(self.lanes) > 1 or not (bound or self._direct):
            views = in_ring.views[0]
            self._copies = {
                k: views[k].new_empty((len(self.lanes), *views[k].shape), device=device.device) for k in self._keys
            }
        # each buffer's rows (a frame each) and its first n rows, as views made once rather than a batch
        copies = self._copies or {}
        self._rows = {k: list(buf.unbind(0)) for k, buf in copies.items()}
        self._batches = {n: {k: buf[:n] for k, buf in copies.items()} for n in range(1, len(self.lanes) + 1)}

    def buffer_bytes(self) -> int:
        """Device memory of the batch buffers this worker keeps (Note [Cameras]); 0 on the CPU."""
        return tensor_bytes(self._copies.values()) if self._copies else 0

    def warm_batch(self, example: dict[str, torch.Tensor]) -> int:
        """Note [First batch]: one batch of a frame per lane through this worker's own copies and the model, before
        READY, into output slots it acquires and gives back unpublished. Every frame is ``example`` (the model's
        inputs for a batch of 1, on its device), and random values of the upstream spec for the keys the worker
        copies that the model does not read (a head copies every feature key). Returns the frames it ran: 0 where
        the worker has no copies of its own (one camera, graphs bound to the slots), or where its output ring was
        published to before (as a restarted worker's usually was), whose slots readers may hold. Raises
        ModelBuildError naming the batch if the model fails on it (a device error: raised as it is, with a note)."""
        if (self._bound and len(self.lanes) == 1) or self.writer.ring.last_seq > 0:
            return 0
        rest = {k: v for k, v in self.spec.upstream.items() if k not in example}
        frame = {**random_inputs(rest, 0, 1, self.dev.device), **example}
        missing = [k for k in self._keys if k not in frame]
        if missing:
            raise ModelBuildError(f"{self.name}: example inputs lack {missing}, which the worker reads")
        one = {k: frame[k][0] for k in self._keys}
        outs: list[SlotInfo] = []
        try:
            for _ in self.lanes:
                slot = self.writer.acquire(timeout=0)
                if slot is None:  # never published to, so only a ring with fewer slots than cameras
                    break
                outs.append(slot)
            if outs:
                try:
                    with torch.inference_mode():
                        self._batch_through([one] * len(outs), [out.tensors for out in outs])
                    self.dev.complete()
                except Exception as e:
                    if poisons(e):  # the device, not the model: raised as it is (Note [Frame errors])
                        e.add_note(f"{self.name}: in a batch of {len(outs)} example frames run before READY")
                        raise
                    raise ModelBuildError(
                        f"{self.name}: a batch of {len(outs)} example frames, run before READY (Note [First batch] "
                        f"in runtime/worker.py), raised {type(e).__name__}: {e}"
                    ) from e
        finally:
            for out in outs:
                self.writer.abort(out)
        return len(outs)

    def run(self, should_stop: Callable[[], bool]) -> None:
        ctl, name = self.control, self.name
        self._should_stop = should_stop
        self._thread = threading.get_ident()
        ctl.set_state(name, RUNNING)
        try:
            # Entered once for the whole loop, not per run (Note [Launch path] in handoff.py)
            with self.dev.active(), torch.inference_mode():
                while not should_stop():
                    ctl.heartbeat(name)
                    self._take()
        finally:
            try:
                self._drop_spare()
            finally:  # whatever the spare did, the held frames are answered
                for tag in list(self._held):
                    self._drop_held(tag)

    def _restream(self) -> None:
        """Before a run, at most every ``RESTREAM_S``: on a stream of the level the governor wrote for this model
        (Note [Stream priority at run time] in device.py). The worker's own thread only, unarmed."""
        now = time.monotonic()
        if not self.dev.cuda or now < self._restream_at:
            return
        self._restream_at = now + RESTREAM_S
        self.dev.use_level(int(self.control.get(self.lanes[0].entry, "stream_level")))

    def _take(self) -> None:
        """One turn of the loop: the frames of the lanes whose gates are open, run as one batch (one camera: a
        batch of one), taken from the ring or launched by the submitting thread; or none within ``poll_s``."""
        ctl = self.control
        active = []
        for lane in self.lanes:
            lane.gate.update(ctl.rate(lane.entry))
            if not lane.gate.paused:
                active.append(lane)
            if lane.tag in self._held and (lane.gate.paused or (self._newest_wins and lane.reader.available())):
                self._drop_held(lane.tag)  # paused since, or a newer frame of its camera came: newest wins
        if not active:
            self._drop_spare()  # not armed while paused: takes no frames from submit
            ctl.set_state(self.name, PAUSED)
            ctl.wait_control(self.name, self.poll_s)
            return
        ctl.set_state(self.name, RUNNING)
        if self._inline is not None and active[0].gate.hz is None:
            self._take_offered()
        else:
            self._drop_spare()  # a rate-limited model decides on each frame first (Note [Inline launch])
            self._take_ring(active)

    def _take_ring(self, active: list[_Lane]) -> None:
        """The frames of ``active`` lanes that come together (within the batch window) from the input ring, run as
        one batch; or none within ``poll_s``. Each gate's rate, read before waiting, is what a rate set since is
        compared with (``_admit``)."""
        held, self._held = self._held, {}
        pins: dict[int, SlotInfo] = dict(held)
        try:
            if len(active) == 1 and not pins:  # one reader: its own wait pins what comes
                slot = active[0].reader.pin(timeout=self.poll_s, should_stop=self._should_stop)
                if slot is None:
                    return
                pins[active[0].tag] = slot
            elif not self._pin_ready(active, pins):
                self._in_ring.wait_any([lane.reader for lane in active], self.poll_s, self._should_stop)
                if not self._pin_ready(active, pins):
                    return
            if len(pins) < len(active):
                self._gather(active, pins)
            admitted = []
            for lane in self.lanes:  # in the configured order
                slot = pins.get(lane.tag)
                if slot is not None and lane.tag in held:  # deferred by the last batch: admitted then
                    admitted.append(slot)
                elif slot is not None:
                    lane.arrived(slot.t_submit)
                    self._check_window(lane)
                    if self._admit(slot, lane.gate.hz):  # a rate set while it waited decides
                        admitted.append(slot)
            if admitted:
                self._run(self._defer(admitted))
        finally:
            for tag, slot in pins.items():
                if tag not in self._held:
                    self._by_tag[tag].reader.release(slot)

    # ------------------------------------------------------------------------------- Note [Cameras]: batches
    def _gather(self, active: list[_Lane], pins: dict[int, SlotInfo]) -> None:
        """Wait at most the batch window for the frames of the other cameras that are due by then; a frame that
        comes later goes in the next batch, counted late."""
        deadline = time.monotonic() + self.window
        while True:
            now = time.monotonic()
            due = [lane for lane in active if lane.tag not in pins and lane.due_by(deadline, now)]
            if not due:
                return
            if now >= deadline:
                for lane in due:  # its frame goes in the next batch
                    self.control.add(lane.entry, "late")
                return
            self._in_ring.wait_any([lane.reader for lane in due], deadline - now, self._should_stop)
            self._pin_ready(due, pins)

    def _check_window(self, lane: _Lane) -> None:
        """Note [Cameras]: a window as long as a camera's frame spacing lets a batch wait for that camera's *next*
        frame once this one's has run, up to a frame's time on every frame. Said once, when the spacing is known,
        and only of a spacing of the default window's 5 ms or more: frames closer than that are a file or a burst
        handed in as fast as the models go (a lockstep run), not a camera's, and the default window is the advice."""
        if self._window_said or len(lane.spacings) < SPACINGS or lane.interval > self.window:
            return
        if lane.interval < _DEFAULT_WINDOW_S:
            return
        self._window_said = True
        log.warning(
            "runtime.batch_window_ms is %g ms, as long as camera %r's frame spacing (%.0f ms): a batch may wait for "
            "that camera's next frame, up to a frame's time on every frame; set it well under the spacing (default 5)",
            self.window * 1e3,
            lane.lane.camera,
            lane.interval * 1e3,
        )

    def _drop_held(self, tag: int) -> None:
        """Give up lane ``tag``'s deferred frame: counted skipped, answered, unpinned."""
        slot = self._held.pop(tag)
        lane = self._by_tag[tag]
        try:
            self.control.skip(lane.entry, "overload")
            self.control.decide(lane.entry, slot.origin, ran=False)
        finally:
            lane.reader.release(slot)

    def _pin_ready(self, lanes: list[_Lane], pins: dict[int, SlotInfo]) -> bool:
        """Pin each lane's next frame that is there; whether any is pinned."""
        for lane in lanes:
            if lane.tag not in pins:
                slot = lane.reader.pin(timeout=0)
                if slot is not None:
                    pins[lane.tag] = slot
        return bool(pins)

    def _defer(self, admitted: list[SlotInfo]) -> list[SlotInfo]:
        """Note [Cameras]: while the model cannot keep up, the least important lane as priorities are now leaves its
        frame for the next batch (counted deferred, kept pinned in ``_held``, not answered), never twice in a row."""
        if len(admitted) < 2 or self._batch_s <= 0:
            return admitted
        intervals = [lane.mean_interval for lane in self.lanes if lane.mean_interval > 0]
        if not intervals or self._batch_s <= min(intervals):
            return admitted
        i = least_important(self.control, [self._by_tag[slot.tag].entry for slot in admitted])
        lane = self._by_tag[admitted[i].tag]
        self._deferred_tag = None if lane.tag == self._deferred_tag else lane.tag
        if self._deferred_tag is None:  # its frame waited a batch the last time: this one runs
            return admitted
        self.control.add(lane.entry, "deferred")
        self._held[lane.tag] = admitted[i]
        return admitted[:i] + admitted[i + 1 :]

    def _admit(self, slot: SlotInfo, rate: float | None) -> bool:
        """Whether the frame in ``slot`` runs, by the rate gate on the frame's own timestamp (``rate.py``); frames
        this model never saw (it was busy) and a frame the gate holds back are counted skipped, and a held-back
        frame is answered (Note [Answered frames]). A rate set while this worker waited for the frame (a pause,
        say) decides: ``Engine.set_rate`` stores the rate before it returns, and a frame published after that is
        seen only after the store, so a pause stops every frame submitted after it."""
        lane = self._by_tag[slot.tag]
        now_rate = self.control.rate(lane.entry)
        if now_rate != rate:
            lane.gate.update(now_rate)
        if slot.missed:  # Note [Give way] in governor.py: skipped, by reason
            self.control.skip(lane.entry, "overload", slot.missed)
        if lane.gate.admit(slot.t_capture, slot.t_submit, slot.missed):
            return True
        self.control.skip(lane.entry, self.control.held_reason(lane.entry))
        self.control.decide(lane.entry, slot.origin, ran=False)
        return False

    # ------------------------------------------------------------------------------------------- one run
    def _run(self, slots: list[SlotInfo], out: SlotInfo | None = None) -> None:
        """One model call on pinned, admitted frames (at most one per lane), each into its own output slot: ``out``
        (one frame, a slot already acquired) or one acquired here (none free: that frame is dropped, counted and
        answered), published with its camera's tag. A run that fails answers every frame (Note [Frame errors])."""
        self._restream()
        t_start = time.monotonic()
        pairs: list[tuple[SlotInfo, SlotInfo]] = []
        for slot in slots:
            if out is None:
                out = self.writer.acquire(timeout=None, should_stop=self._should_stop)
            if out is None:
                entry = self._by_tag[slot.tag].entry
                self.control.add(entry, "dropped")
                self.control.decide(entry, slot.origin, ran=False)
            else:
                pairs.append((slot, out))
            out = None
        if not pairs:
            return
        try:
            self._launch(pairs)
        except BaseException as e:
            self._failed(pairs, e)
            return
        self._publish(pairs, t_start)
        took = time.monotonic() - t_start
        self._batch_s = took if self._batch_s <= 0 else self._batch_s + 0.25 * (took - self._batch_s)

    def _launch(self, pairs: list[tuple[SlotInfo, SlotInfo]]) -> None:
        """Queue the model's work on each frame's slot into its output slot (on the CPU: do it). Gives the output
        slots back if that raises. Called by this worker's thread, or, for one frame, by the submitting thread
        (Note [Inline launch])."""
        if self._in_events is not None:  # each input slot was published queued: read it only after that work
            for slot, _ in pairs:
                self.dev.wait_on(self._in_events.events[slot.index])
        try:
            if threading.get_ident() == self._thread:  # run() made the stream current, inference mode on
                self._run_model(pairs)
            elif self._bound:  # graph launches dispatch no tensor ops: no inference mode needed
                slot, out = pairs[0]
                self.model.run_bound_on(self.dev.stream, slot.index, out.index)  # type: ignore[attr-defined]
            else:
                with self.dev.active(), torch.inference_mode():
                    self._run_model(pairs)
            if self._out_events is not None:
                for _, out in pairs:
                    self.dev.mark(self._out_events.events[out.index])
        except BaseException:
            for _, out in pairs:
                self.writer.abort(out)
            raise

    def _run_model(self, pairs: list[tuple[SlotInfo, SlotInfo]]) -> None:
        n = len(pairs)
        if self._bound and n == 1:  # graphs captured for this pair of slots
            self.model.run_bound(pairs[0][0].index, pairs[0][1].index)  # type: ignore[attr-defined]
            return
        self._batch_through([slot.tensors for slot, _ in pairs], [out.tensors for _, out in pairs])

    def _batch_through(self, frames: list[dict[str, torch.Tensor]], outs: list[dict[str, torch.Tensor]]) -> None:
        """The model on ``frames`` (one frame's input tensors each) as one batch, each frame's outputs copied into
        its own ``outs`` tensors."""
        n = len(frames)
        outputs = self.model(self._inputs(frames))
        if n not in self._checked:
            check_outputs(self.name, self.output_spec, outputs, batch=n)
            self._checked.add(n)
        dsts = [t for out in outs for t in out.values()]
        srcs = [outputs[k][i] for i, out in enumerate(outs) for k in out]
        if not dsts:  # a model of no outputs
            return
        if dsts[0].device == srcs[0].device:  # Note [One call for a batch's copies]
            torch._foreach_copy_(dsts, srcs, non_blocking=True)
        else:  # to host output slots: a copy each
            for dst, src in zip(dsts, srcs):
                dst.copy_(src, non_blocking=True)

    def _inputs(self, frames: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
        """The frames as one batch (Note [Executor contract] in backends/base.py): one frame's slot viewed, or
        the frames copied into the batch buffers."""
        if len(frames) == 1 and self._direct:
            return {k: frames[0][k].unsqueeze(0) for k in self._keys}
        assert self._copies is not None
        n, rows = len(frames), self._rows
        if self._direct and rows:  # every key of every frame in one call (Note [One call for a batch's copies])
            dsts = [rows[k][i] for k in rows for i in range(n)]
            torch._foreach_copy_(dsts, [f[k] for k in rows for f in frames], non_blocking=True)
        else:  # host slots to the device: a copy each
            for k, row in rows.items():
                for i, f in enumerate(frames):
                    row[i].copy_(f[k], non_blocking=True)
        return dict(self._batches[n])

    def _publish(self, pairs: list[tuple[SlotInfo, SlotInfo]], t_start: float) -> None:
        """Count and publish the outputs of one model call whose work ``_launch`` queued: all of them before any
        wait for the device, so a batch's frames reach the next models together; answers them all if that
        fails. The caller then releases the input slots."""
        try:
            self._finish(pairs, t_start)
        except BaseException:
            for slot, _ in pairs:
                self.control.decide(self._by_tag[slot.tag].entry, slot.origin, ran=False)
            raise
        self.control.add(self._by_tag[pairs[0][0].tag].entry, "batches")
        if len(pairs) > 1:
            for slot, _ in pairs:
                self.control.add(self._by_tag[slot.tag].entry, "batched")

    def _finish(self, pairs: list[tuple[SlotInfo, SlotInfo]], t_start: float) -> None:
        ctl = self.control
        handoff = self._out_events
        if handoff is None:
            try:
                self.dev.complete()  # Note [Device sync]: publish only what is complete
            except BaseException:
                for _, out in pairs:
                    self.writer.abort(out)
                raise
        # Counters first, then publish: whoever sees the output also sees it counted.
        t_end = time.monotonic()
        for slot, out in pairs:
            entry = self._by_tag[slot.tag].entry
            ctl.record_run(entry, t_start, t_end - t_start, t_end - slot.t_submit, slot.frame_id)
            self.writer.publish(out, slot.frame_id, slot.t_capture, slot.t_submit, slot.origin, tag=slot.tag)
            ctl.decide(entry, slot.origin, ran=True, wake=self.spec.notify_output)
        if handoff is not None:
            # The input slot is released (by run) only after the work that read it is done; the run's times
            # are the device's, not the queueing's.
            self.dev.complete()
            t_end = time.monotonic()
            for slot, out in pairs:
                ctl.amend_last_run(self._by_tag[slot.tag].entry, t_end - t_start, t_end - slot.t_submit)
                if self.spec.notify_output:
                    # Note [Result hand-off]: when it was there; wakes readers waiting for done results
                    handoff.mark_done(self.writer.ring, out, t_end)
            if self.spec.notify_output:
                ctl.notify_output()

    def _failed(self, pairs: list[tuple[SlotInfo, SlotInfo]], error: BaseException) -> None:
        """A run raised ``error`` (its output slots are given back): answer its frames, then count and log the
        error and go on, or raise it again where it leaves this worker unable to go on (Note [Frame errors])."""
        poisoned = poisons(error)
        if not poisoned:  # counted before the frames are answered: whoever the answer wakes sees the count
            self.control.add(self.name, "errors")
            self.control.set_error(self.name, describe_exception(self.name, error))
        for slot, _ in pairs:
            self.control.decide(self._by_tag[slot.tag].entry, slot.origin, ran=False)
        if poisoned:
            raise error
        where = traceback.extract_tb(error.__traceback__)[-1:]
        reason = (type(error).__name__, *((where[0].filename, where[0].lineno or 0) if where else ("", 0)))
        if reason not in self._reasons:  # once per reason: a model failing on every frame does not flood the log
            self._reasons.add(reason)
            log.error(
                "%s raised on frame %s and goes on; frames it raises on get no output from it (counted in "
                "stats' errors; the same error is not logged again): %s: %s",
                self.name,
                pairs[0][0].frame_id,
                type(error).__name__,
                error,
            )

    # ---------------------------------------------------------------------- Note [Inline launch], worker side
    def _take_offered(self) -> None:
        """A frame as a batch of one: launched by the submitting thread, or taken from the ring; or none within
        ``poll_s``. Only while the model is unlimited: a rate-limited one decides on each frame's timestamp before
        any work is queued for it (``_take_ring``). A rate set since the loop read it (``Engine.set_rate`` sets
        it, then takes the offer's lock to wake us) takes nothing: the loop's gate decides again."""
        offer, lane, ctl = self._inline, self.lanes[0], self.control
        assert offer is not None
        if self._spare is None:
            self._spare = self.writer.acquire(timeout=None, should_stop=self._should_stop)
            if self._spare is None:
                if not self._should_stop():
                    ctl.add(lane.entry, "dropped")
                return
        done = None
        self._restream()  # not armed yet: the submitting thread launches on the stream it finds once armed
        with offer.cond:  # not armed before this: no launch can be waiting here
            if ctl.rate(lane.entry) is not None:
                return  # a pause or limit set since the loop read the rate: no frame submitted since may run
            slot = lane.reader.pin(timeout=0)
            if slot is None:
                spare = self._spare
                offer.arm(
                    lambda frame: self._launch([(frame, spare)]),
                    lane.reader,
                    lambda: ctl.rate(lane.entry) is None,
                )
                try:
                    offer.cond.wait(self.poll_s)
                finally:
                    offer.disarm()
                done = offer.take_done()
        if done is None:
            if slot is None:
                return  # nothing came: the spare slot stays for the next arming
            try:  # a frame was in the ring: run it here
                if self._admit(slot, None):
                    out, self._spare = self._spare, None
                    self._run([slot], out)
            finally:
                lane.reader.release(slot)
            return
        out, self._spare = self._spare, None
        slot, t_start, error = done
        try:
            if error is not None:  # the launch failed in the submitting thread; out was given back there
                self._failed([(slot, out)], error)
                return
            # launched while unlimited: the gate only keeps its clock; frames missed meanwhile are counted
            lane.gate.admit(slot.t_capture, slot.t_submit, slot.missed)
            if slot.missed:
                ctl.skip(lane.entry, "overload", slot.missed)
            self._publish([(slot, out)], t_start)
        finally:
            lane.reader.release(slot)

    def _drop_spare(self) -> None:
        """Give back the output slot kept for arming: paused, rate-limited or leaving. The worker is never armed
        here: it arms only inside ``_take_offered``, which disarms and takes any launch under the lock."""
        if self._spare is not None:
            self.writer.abort(self._spare)
            self._spare = None


def poisons(error: BaseException) -> bool:
    """Whether ``error`` leaves its worker unable to go on (Note [Frame errors]): not a Python exception
    (KeyboardInterrupt, SystemExit), or a CUDA error, after which the process's CUDA context is unusable."""
    if not isinstance(error, Exception):
        return True
    if isinstance(error, getattr(torch, "AcceleratorError", ())):  # torch >= 2.8 raises CUDA errors as this
        return True
    return isinstance(error, RuntimeError) and any(mark in str(error) for mark in _CUDA_ERRORS)


#: How earlier torch versions word a CUDA error (a RuntimeError): "CUDA error: an illegal memory access ...".
_CUDA_ERRORS = ("CUDA error", "CUDA driver error")


def input_keys(spec: WorkerSpec, in_ring: SlotRing) -> list[str]:
    """The input ring's keys a model reads: its upstream spec's (a head), or all of them (the foundation)."""
    return list(spec.upstream) or list(in_ring.layout.keys)


def describe_exception(name: str, exc: BaseException) -> str:
    """``name (pid P): Type: message`` and the traceback. A ModelBuildError raised for its own reason (no other error
    chained to it, explicitly or while handling one: a missing or unreadable checkpoint, a model that does not fit
    its config) says what is wrong and the fix in its message; its traceback would bury that line under vpengine's
    frames and repeat it, so it has none."""
    head = f"{name} (pid {os.getpid()}): {type(exc).__name__}: {exc}"
    alone = exc.__cause__ is None and (exc.__context__ is None or exc.__suppress_context__)
    if isinstance(exc, ModelBuildError) and alone:
        return head
    tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    return f"{head}\n{tb}"
