"""The one worker loop, used for the foundation model and every head, in a thread or in a child process.

``WorkerCore`` holds the logic and no IPC (it is handed rings and a control block that are already mapped), so the
same object runs in-process under tests and debuggers, in a thread (thread mode), or inside a spawned child
(process mode, ``process.py``). One iteration::

    rate gate -> pin newest input (with timeout) -> acquire output slot -> stage inputs on the device
      -> model -> copy outputs into the slot -> device sync -> publish output -> release input -> counters

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
Several cameras feed one engine: one backbone's weights, one set of workers and mailboxes. Every frame is tagged with
its camera (Note [Tagged slots] in transport/ring.py) and a model keeps one *lane* per camera it serves: that
camera's reader of its input ring, its rate gate, and its control-block entry (``model@camera``: rate, counters,
latencies, answered frames), so rates, counts and Note [Answered frames] hold per camera. A model with several lanes
takes its frames as one batch (``_take_batch``): it waits for the first frame of any camera, then at most
``runtime.batch_window_ms`` for the other cameras whose next frame is due by then; a camera whose frame comes later
goes in the next batch, counted ``late``. The frames the gates admit are copied into preallocated batch buffers (one
frame per lane) and run as one batch through the model (Note [Batched models] in models/base.py; a compiled model
has a graph for every batch size up to its lanes), and each frame's outputs are copied into its own slot and published
with its camera's tag. When the model cannot keep up (its last batch took longer
than the cameras' frame interval), the camera last in the configured order leaves its frame for the next batch,
counted ``deferred`` (never twice in a row, so no camera starves): the first cameras keep their rate and latency.
The deferred frame stays pinned and unanswered, and runs in the next batch unless a newer frame of its camera is
there by then (newest wins: the deferred one is then skipped and answered). A deferral is a guess from wall-clock
averages and may be wrong (one slow batch under load is enough), so it must never cost a frame on its own: a caller
that waits for every frame (lockstep pacing) gets every output, only a batch later.
With one camera nothing of this runs: the model takes its frames one by one as before (and may take them from the
submitting thread, Note [Inline launch]).

The hand-offs that thread mode on CUDA uses between models (events instead of host waits, the submitting thread
launching the foundation's work) live in handoff.py.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from vpengine.config import EngineConfig, load_config
from vpengine.models.base import Role, check_outputs
from vpengine.models.build import build_lock, build_model, model_config
from vpengine.runtime.control import PAUSED, POLL_S, RUNNING, ControlBlock, ControlDesc, camera_entry
from vpengine.runtime.device import DeviceContext
from vpengine.runtime.handoff import WorkerHandoff, inline_wanted
from vpengine.runtime.priority import stream_level
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
    in_ring: RingDesc
    in_reader: str
    out_ring: RingDesc
    notify_output: bool
    control: ControlDesc | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def engine_config(self) -> EngineConfig:
        return load_config(self.config)


@dataclass
class _Lane:
    """One camera's share of a model's work (Note [Cameras])."""

    camera: str
    tag: int
    reader: RingReader
    gate: RateGate
    entry: str  # its control-block entry
    last_arrival: float = -math.inf  # when its last frame reached the engine (monotonic)
    interval: float = 0.0  # moving average of its frames' spacing (0: not known yet)
    deferred: bool = False  # its last frame was left for a later batch (Note [Cameras])

    def arrived(self, t: float) -> None:
        if self.last_arrival > -math.inf and t > self.last_arrival:
            step = t - self.last_arrival
            self.interval = step if self.interval <= 0 else self.interval + 0.125 * (step - self.interval)
        self.last_arrival = t

    def due_by(self, deadline: float, now: float) -> bool:
        """Whether its next frame should come by ``deadline``: it delivers frames, and the next is due then."""
        if self.interval <= 0:
            return False
        live = now - self.last_arrival < 3 * self.interval
        return live and self.last_arrival + self.interval <= deadline


class WorkerCore:
    """The loop of one model. Construct with mapped rings; ``run`` until ``should_stop`` says so."""

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
        cfg = spec.engine_config()
        cameras = cfg.camera_names()
        # Note [Cameras]: one lane per camera this model serves; a one-camera engine has one lane, named after the
        # model, with the model's own reader and control-block entry
        self.lanes = [
            _Lane(
                camera=c,
                tag=cameras.index(c),
                reader=in_ring.reader(spec.in_reader if len(cameras) == 1 else f"{spec.name}@{c}"),
                gate=RateGate(),
                entry=camera_entry(spec.name, c, cameras),
            )
            for c in cfg.model_cameras(spec.name)
        ]
        self._by_tag = {lane.tag: lane for lane in self.lanes}
        self.window = cfg.runtime.batch_window_ms * 1e-3
        self.reader, self.gate = self.lanes[0].reader, self.lanes[0].gate  # the one-camera path
        self.writer = out_ring.writer()
        self.control = control
        self.dev = device
        self.poll_s = poll_s
        self._checked = False
        self._should_stop: Callable[[], bool] = lambda: False
        self._keys = input_keys(spec, in_ring)
        self._in_ring = in_ring
        handoff = handoff or WorkerHandoff()
        # Notes [Event hand-off], [Result hand-off] in handoff.py: this worker waits on the device for the events of
        # its input slots, and publishes queued work with the events of its output slots.
        self._in_events = handoff.in_events
        self._out_events = handoff.out_events
        # Note [Inline launch]: the submitting thread may queue this (foundation) worker's work
        self._inline = handoff.inline
        self._thread: int | None = None  # the thread running the loop (Note [Launch path])
        self._spare: SlotInfo | None = None  # the output slot an armed worker offers
        self._batch_s = 0.0  # moving average of how long a batch takes (Note [Cameras])
        self._held: dict[int, SlotInfo] = {}  # lane tag -> its deferred frame, pinned, admitted (Note [Cameras])
        # The executor runs straight from the slots (Note [Slot-bound runs]): no staging, no copies here.
        self._bound = bound
        # Note [Cameras]: the frames of a batch are copied into preallocated buffers of one frame per lane
        self._batch_in: dict[str, torch.Tensor] | None = None
        self._checked_batch = False
        if len(self.lanes) > 1:
            self._batch_in = {
                k: in_ring.views[0][k].new_empty((len(self.lanes), *in_ring.views[0][k].shape), device=device.device)
                for k in self._keys
            }
        # Inputs live wherever their ring lives; a model on another device reads preallocated staging copies.
        self._staging: dict[str, torch.Tensor] | None = None
        if not bound and in_ring.data_region.device != device.device:
            self._staging = {k: torch.empty_like(in_ring.views[0][k], device=device.device) for k in self._keys}

    def _inputs(self, slot: SlotInfo) -> dict[str, torch.Tensor]:
        """The slot's one frame as a batch of one (views; Note [Executor contract] in backends/base.py)."""
        if self._staging is None:
            return {k: slot.tensors[k].unsqueeze(0) for k in self._keys}
        for k, t in self._staging.items():
            t.copy_(slot.tensors[k], non_blocking=True)
        return {k: t.unsqueeze(0) for k, t in self._staging.items()}

    def run(self, should_stop: Callable[[], bool]) -> None:
        ctl, name = self.control, self.name
        self._should_stop = should_stop
        self._thread = threading.get_ident()
        ctl.set_state(name, RUNNING)
        try:
            # Entered once for the whole loop, not per run (Note [Launch path])
            with self.dev.active(), torch.inference_mode():
                self._loop(should_stop)
        finally:
            try:
                self._drop_spare()
            finally:  # whatever the spare did, the held frames are answered
                for tag in list(self._held):
                    self._drop_held(tag)

    def _loop(self, should_stop: Callable[[], bool]) -> None:
        ctl, name = self.control, self.name
        entry = self.lanes[0].entry
        while not should_stop():
            ctl.heartbeat(name)
            if len(self.lanes) > 1:
                self._take_batch()
                continue
            rate = ctl.rate(entry)
            self.gate.update(rate)
            if self.gate.paused:
                self._drop_spare()  # not armed while paused: takes no frames from submit
                ctl.set_state(name, PAUSED)
                ctl.wait_control(name, self.poll_s)
                continue
            ctl.set_state(name, RUNNING)
            if self._inline is not None and rate is None:
                self._take_inline()
            else:
                self._drop_spare()  # a rate-limited model decides on each frame first (Note [Inline launch])
                self._take(rate)

    def _take(self, rate: float | None) -> None:
        """One frame from the ring, or none within ``poll_s``; ``rate`` is the rate read before waiting."""
        slot = self.reader.pin(timeout=self.poll_s, should_stop=self._should_stop)
        if slot is None:
            return
        try:
            if self._admit(slot, rate):
                self._step(slot)
        finally:
            self.reader.release(slot)

    # ------------------------------------------------------------------------------- Note [Cameras]: batches
    def _take_batch(self) -> None:
        """The frames of every camera that come together (within the batch window), run as one batch; or none
        within ``poll_s``."""
        ctl = self.control
        active = []
        for lane in self.lanes:
            lane.gate.update(ctl.rate(lane.entry))
            if not lane.gate.paused:
                active.append(lane)
            if lane.tag in self._held and (lane.gate.paused or lane.reader.available()):
                self._drop_held(lane.tag)  # paused since, or a newer frame of its camera came: newest wins
        if not active:
            ctl.set_state(self.name, PAUSED)
            ctl.wait_control(self.name, self.poll_s)
            return
        ctl.set_state(self.name, RUNNING)
        held, self._held = self._held, {}
        pins: dict[int, SlotInfo] = dict(held)
        try:
            if not self._pin_ready(active, pins):
                self._in_ring.wait_any([lane.reader for lane in active], self.poll_s, self._should_stop)
                if not self._pin_ready(active, pins):
                    return
            deadline = time.monotonic() + self.window
            while True:
                now = time.monotonic()
                due = [lane for lane in active if lane.tag not in pins and lane.due_by(deadline, now)]
                if not due:
                    break
                if now >= deadline:
                    for lane in due:  # its frame goes in the next batch
                        ctl.add(lane.entry, "late")
                    break
                self._in_ring.wait_any([lane.reader for lane in due], deadline - now, self._should_stop)
                self._pin_ready(due, pins)
            admitted = []
            for lane in self.lanes:  # in priority order
                slot = pins.get(lane.tag)
                if slot is not None and lane.tag in held:  # deferred by the last batch: admitted then
                    admitted.append(slot)
                elif slot is not None:
                    lane.arrived(slot.t_submit)
                    if self._admit(slot, lane.gate.hz):  # a rate set while it waited decides
                        admitted.append(slot)
            self._run_batch(self._defer(admitted))
        finally:
            for tag, slot in pins.items():
                if tag not in self._held:
                    self._by_tag[tag].reader.release(slot)

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
        """Note [Cameras]: while the model cannot keep up, the last camera in priority order leaves its frame for
        the next batch (counted deferred, kept pinned in ``_held``, not answered), never twice in a row."""
        if len(admitted) < 2 or self._batch_s <= 0:
            return admitted
        intervals = [lane.interval for lane in self.lanes if lane.interval > 0]
        if not intervals or self._batch_s <= min(intervals):
            return admitted
        last = self._by_tag[admitted[-1].tag]
        if last.deferred:
            last.deferred = False
            return admitted
        last.deferred = True
        self.control.add(last.entry, "deferred")
        self._held[last.tag] = admitted[-1]
        return admitted[:-1]

    def _run_batch(self, slots: list[SlotInfo]) -> None:
        """Run admitted frames of several cameras as one batch and publish each output in its own slot."""
        if not slots:
            return
        t0 = time.monotonic()
        if len(slots) == 1:
            self._step(slots[0])
        else:
            self._step_batch(slots, t0)
        took = time.monotonic() - t0
        self._batch_s = took if self._batch_s <= 0 else self._batch_s + 0.25 * (took - self._batch_s)

    def _step_batch(self, slots: list[SlotInfo], t_start: float) -> None:
        """One model call for the frames in ``slots`` (pinned, admitted, one per camera): each frame gets an output
        slot (none free: that frame is dropped, counted and answered), the inputs are copied into the preallocated
        batch buffers, and each frame's outputs into its own slot, published with its camera's tag. A run that
        fails answers every frame of the batch and gives every output slot back."""
        pairs: list[tuple[SlotInfo, SlotInfo]] = []
        for slot in slots:
            out = self.writer.acquire(timeout=None, should_stop=self._should_stop)
            if out is None:
                entry = self._by_tag[slot.tag].entry
                self.control.add(entry, "dropped")
                self.control.decide(entry, slot.origin, ran=False)
            else:
                pairs.append((slot, out))
        launched = published = False
        try:
            if pairs:
                self._launch_batch(pairs)
                launched = True
                self._finish_all(pairs, t_start)  # gives every slot back if the device work failed
                published = True
                if len(pairs) > 1:
                    for slot, _ in pairs:
                        self.control.add(self._by_tag[slot.tag].entry, "batched")
        finally:
            if not published:
                for slot, out in pairs:
                    if not launched:
                        self.writer.abort(out)
                    self.control.decide(self._by_tag[slot.tag].entry, slot.origin, ran=False)

    def _launch_batch(self, pairs: list[tuple[SlotInfo, SlotInfo]]) -> None:
        """Queue the model's work on a batch of frames (on the CPU: do it), each into its output slot."""
        assert self._batch_in is not None
        n = len(pairs)
        if self._in_events is not None:  # each input slot was published queued: read it only after that work
            for slot, _ in pairs:
                self.dev.wait_on(self._in_events.events[slot.index])
        for k, buf in self._batch_in.items():
            for i, (slot, _) in enumerate(pairs):
                buf[i].copy_(slot.tensors[k], non_blocking=True)
        outputs = self.model({k: buf[:n] for k, buf in self._batch_in.items()})
        if not self._checked_batch:
            check_outputs(self.name, self.output_spec, outputs, batch=n)
            self._checked_batch = True
        for i, (_, out) in enumerate(pairs):
            for k, t in out.tensors.items():
                t.copy_(outputs[k][i], non_blocking=True)
            if self._out_events is not None:
                self.dev.mark(self._out_events.events[out.index])

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

    def _step(self, slot: SlotInfo, out: SlotInfo | None = None) -> None:
        """One run on a pinned, admitted ``slot``, into ``out`` (an output slot already acquired) or one it
        acquires. A run that publishes nothing (no output slot, or the model raised) still answers the frame."""
        t_start = time.monotonic()
        entry = self._by_tag[slot.tag].entry
        ran = False
        try:
            if out is None:
                out = self.writer.acquire(timeout=None, should_stop=self._should_stop)
            if out is None:
                self.control.add(entry, "dropped")
                return
            self._launch(slot, out)
            self._finish(slot, out, t_start)
            ran = True
        finally:
            if not ran:
                self.control.decide(entry, slot.origin, ran=False)

    def _launch(self, slot: SlotInfo, out: SlotInfo) -> None:
        """Queue the model's work from ``slot`` into ``out`` (on the CPU: do it). Gives ``out`` back if that raises.
        Called by this worker's thread, or by the submitting thread (Note [Inline launch])."""
        if self._in_events is not None:  # the slot's writer published it queued: read it only after that work
            self.dev.wait_on(self._in_events.events[slot.index])
        try:
            if threading.get_ident() == self._thread:  # run() made the stream current, inference mode on
                self._run_model(slot, out)
            elif self._bound:  # graph launches dispatch no tensor ops: no inference mode needed
                self.model.run_bound_on(self.dev.stream, slot.index, out.index)  # type: ignore[attr-defined]
            else:
                with self.dev.active(), torch.inference_mode():
                    self._run_model(slot, out)
            if self._out_events is not None:
                self.dev.mark(self._out_events.events[out.index])
        except BaseException:
            self.writer.abort(out)
            raise

    def _run_model(self, slot: SlotInfo, out: SlotInfo) -> None:
        if self._bound:
            self.model.run_bound(slot.index, out.index)  # type: ignore[attr-defined]
            return
        outputs = self.model(self._inputs(slot))
        if not self._checked:
            check_outputs(self.name, self.output_spec, outputs)
            self._checked = True
        for k, t in out.tensors.items():
            t.copy_(outputs[k][0], non_blocking=True)

    def _finish(self, slot: SlotInfo, out: SlotInfo, t_start: float) -> None:
        """Count and publish a run whose work ``_launch`` queued; the caller then releases ``slot``."""
        self._finish_all([(slot, out)], t_start)

    def _finish_all(self, pairs: list[tuple[SlotInfo, SlotInfo]], t_start: float) -> None:
        """Count and publish the outputs of one model call (a frame, or a batch of the cameras' frames): all of
        them before any wait for the device, so a batch's frames reach the next models together."""
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
            name = self._by_tag[slot.tag].entry
            ctl.record_run(name, t_start, t_end - t_start, t_end - slot.t_submit, slot.frame_id)
            self.writer.publish(out, slot.frame_id, slot.t_capture, slot.t_submit, slot.origin, tag=slot.tag)
            ctl.decide(name, slot.origin, ran=True, wake=self.spec.notify_output)
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

    # ---------------------------------------------------------------------- Note [Inline launch], worker side
    def _take_inline(self) -> None:
        """One frame, taken from the ring or launched by the submitting thread, or none within ``poll_s``. Only
        while the model is unlimited: a rate-limited one decides on each frame's timestamp before any work is
        queued for it (``_take``). A rate set since the loop read it (``Engine.set_rate`` sets it, then takes the
        offer's lock to wake us) takes nothing: the loop's gate decides again."""
        offer = self._inline
        assert offer is not None
        if self._spare is None:
            self._spare = self.writer.acquire(timeout=None, should_stop=self._should_stop)
            if self._spare is None:
                if not self._should_stop():
                    self.control.add(self.name, "dropped")
                return
        done = None
        with offer.cond:  # not armed before this: no launch can be waiting here
            if self.control.rate(self.name) is not None:
                return  # a pause or limit set since the loop read the rate: no frame submitted since may run
            slot = self.reader.pin(timeout=0)
            if slot is None:
                spare = self._spare
                offer.arm(
                    lambda frame: self._launch(frame, spare),
                    self.reader,
                    lambda: self.control.rate(self.name) is None,
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
                    self._step(slot, out=out)
            finally:
                self.reader.release(slot)
            return
        out, self._spare = self._spare, None
        slot, t_start, error = done
        ran = False
        try:
            if error is not None:
                raise error  # the launch failed in the submitting thread; out was given back there
            # launched while unlimited: the gate only keeps its clock; frames missed meanwhile are counted
            self.gate.admit(slot.t_capture, slot.t_submit, slot.missed)
            if slot.missed:
                self.control.skip(self.name, "overload", slot.missed)
            self._finish(slot, out, t_start)
            ran = True
        finally:
            if not ran:
                self.control.decide(self.name, slot.origin, ran=False)
            self.reader.release(slot)

    def _drop_spare(self) -> None:
        """Give back the output slot kept for arming: paused, rate-limited or leaving. The worker is never armed
        here: it arms only inside ``_take_inline``, which disarms and takes any launch under the lock."""
        if self._spare is not None:
            self.writer.abort(self._spare)
            self._spare = None


def input_keys(spec: WorkerSpec, in_ring: SlotRing) -> list[str]:
    """The input ring's keys a model reads: its upstream spec's (a head), or all of them (the foundation)."""
    return list(spec.upstream) or list(in_ring.layout.keys)


def describe_exception(name: str, exc: BaseException) -> str:
    tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))
    return f"{name} (pid {os.getpid()}): {type(exc).__name__}: {exc}\n{tb}"


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


def prepare_worker(
    spec: WorkerSpec,
    in_ring: SlotRing,
    out_ring: SlotRing,
    control: ControlBlock,
    own_process: bool,
    handoff: WorkerHandoff | None = None,
) -> WorkerCore:
    """Build the model on its device, warm it up (allocations happen here, before READY), return its loop."""
    from vpengine.backends import make_executor
    from vpengine.runtime.control import LOADING, READY

    cfg = spec.engine_config()
    mcfg = model_config(cfg, spec.name)
    device = torch.device(cfg.device)
    if own_process:
        # A GPU worker needs no CPU thread pool: left at its default (one thread per core, in every worker), the
        # OpenMP threads spin after any small CPU op and burn cores for nothing.
        torch.set_num_threads(mcfg.cpu_threads)
    control.set_state(spec.name, LOADING)
    control.set(spec.name, "pid", os.getpid())
    dev = DeviceContext(device, priority=stream_level(cfg, spec.name))  # Note [Give way] in governor.py
    if dev.cuda:
        _register_host_rings(in_ring, out_ring)
        from vpengine.transport.cuda_vmm import mps_enabled

        try:
            control.set(spec.name, "mps_active", int(mps_enabled(device.index or 0)))
        except Exception:  # the bindings are optional in thread mode; MPS status is informational
            control.set(spec.name, "mps_active", 0)
    with dev.active():
        model = build_model(cfg, spec.name, spec.role, spec.upstream, spec.upstream_meta, device, plan_only=False)
        # Under the build lock too: a CUDA graph capture (compile backend) must not overlap another thread building
        # a model, whose layer init draws from the CUDA RNG that the capture has claimed (seen on an H100).
        with build_lock:
            executor = make_executor(
                model,
                mcfg.backend,
                device,
                spec.name,
                options=mcfg.backend_options,
                precision=mcfg.precision or cfg.precision,
                max_batch=len(cfg.model_cameras(spec.name)),  # Note [Cameras]: a frame of each camera at once
            )
            # Warm-up on random inputs: first-run allocations, autotuning and compilation all happen before READY,
            # so the steady state allocates nothing (Invariant: constant memory).
            with torch.inference_mode():
                check_outputs(spec.name, model.output_spec, executor(model.example_inputs(device)))
                keys = input_keys(spec, in_ring)
                bound = executor.bind([{k: v[k] for k in keys} for v in in_ring.views], list(out_ring.views))
        dev.complete()
    control.set(spec.name, "device_mem_bytes", dev.memory_bytes())
    control.set(spec.name, "started_at", time.monotonic())
    if handoff is not None and not inline_wanted(dev.cuda, bound):
        handoff = WorkerHandoff(handoff.in_events, handoff.out_events, None)  # Note [Inline launch]
    core = WorkerCore(spec, executor, model.output_spec, in_ring, out_ring, control, dev, bound=bound, handoff=handoff)
    control.heartbeat(spec.name)
    control.set_state(spec.name, READY)
    return core
