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

Note [Event hand-off]
~~~~~~~~~~~~~~~~~~~~~
Note [Device sync] makes a writer wait on the host until the work that filled a slot is done, then publish it. For
the hop from the foundation model to the heads in thread mode that wait sits on every frame's critical path twice
over: the foundation thread wakes from the driver (0.1-0.2 ms), then each head thread wakes from the ring and only
then starts queueing its own work, while the GPU idles. In thread mode on CUDA (``runtime.feature_handoff: event``,
the default) the foundation worker instead records a CUDA event per feature slot right after queueing its work and
publishes the slot at once; a head that pins the slot makes its own stream wait on that event (``cudaStreamWaitEvent``,
no host wait) before it reads, so the heads' work is queued while the features are still being computed and starts
the moment they are done. What Note [Device sync] protects still holds: no head's device work reads a slot before
the work that filled it is complete (stream order), and the foundation worker still waits for its own work before it
releases its input slot, so the caller's frame is never overwritten while it is read. Heads hand their results to
the host on the host's terms as before: they sync, then publish. Process mode keeps the host hand-off (its events
would have to cross processes), and so does the CPU, where work is synchronous. The foundation's run is counted
when it is published and its times corrected once its work is done (``ControlBlock.amend_last_run``).

Note [Result hand-off]
~~~~~~~~~~~~~~~~~~~~~~
The last hop, from a head to the caller waiting for the frame, cost two wake-ups after the device was done: the
head's thread woke from the driver, published, and woke the caller, who then pinned and read the result (on an H100,
0.2 ms of a 3.4 ms depth + seg frame). In thread mode on CUDA (``runtime.result_handoff: event``, the default) a
head records a blocking CUDA event per output slot after queueing its work and the copy to the host, publishes at
once, and wakes the caller, who pins the result while the device still computes it. ``Engine.wait`` then sleeps in
the driver on the slot's event (``SlotRing.wait_done``) and returns as soon as the device is done: the wake-ups happen
while the device works, not after. The head's thread still waits for its own work before it releases its input
slot, counts the run by its device time (``amend_last_run``), and records when the work was done
(``SlotRing.mark_done``), which is each result's ``latency``; then it wakes readers again. ``Engine.results`` and
``Engine.latest`` take only results that are done (``pin(done=True)``): they never block on device work, and a
FIFO reader never takes a result out of order. No reader reads a slot before its content is there: ``wait_done``
is called on every pinned result before its content is read (borrowed arrays over it may be made before). Process mode keeps the host hand-off (its events
would have to cross processes), and so does the CPU. A wait in the driver cannot be cut short, so ``Engine.wait``
waits there only for a result that its head's recent results say will be done before the caller's timeout; any
other it leaves pinned by nobody until the head, having seen the work done, wakes it (or the timeout comes).

Measured on an H200 (thread mode, compiled depth + seg, frame slot, variants alternated round by round on one
engine, median of 8-14 rounds' p50s; benchmarks/results/h200/ab_result_handoff_*.json): with the caller sleeping in
the driver this alone gains little (2.47-2.51 against 2.45-2.53 ms with the host hand-off): its wake-up costs as
much as the head thread's did. What the hand-off makes possible is spending CPU on that one wake-up only, which
``runtime.wait_spin_us`` (default 200) does: ``wait_done`` sleeps through the part of the wait that the head's
recent results predict (learnt from when each was done), then polls the event, offering the interpreter lock
between polls with ``os.sched_yield`` (``time.sleep(0)`` sleeps out the timer slack, about 55 us: 2.367 against
2.302 ms), until a window past the predicted end: ``wait_spin_us`` plus twice the results' recent spread, at most
three times ``wait_spin_us``. A result later than that is waited for in the driver, asleep. So the CPU a wait
spends is bounded however late a head is; the first version spun in the driver (default-flag events) until the
result came, which is why it was off by default. Depth + seg, three machines: 2.302, 2.308 and 2.341 ms with the
poll against 2.439, 2.457 and 2.477 asleep, as fast as that driver spin (2.313, 2.314) or spinning through the whole
wait (2.301, 2.302), for 0 to 0.29 ms more of the caller's CPU a frame (1.36-1.89 ms, the frame's 6 MB write
included). Eight depth heads, whose results' times vary more: 5.70 ms with the poll against 5.69-5.74 asleep and
5.61-5.65 with the unbounded driver spin; the spread in the window took the waits the poll left to the driver from
21% to 7% (ab_result_handoff_poll{,_spread}_depth8.json). Before any wait for the
device, ``Engine.wait`` borrows every result it pinned (``Engine._copy_out``: the arrays over a slot read nothing
of its content), so that what is left once the last result is there is little more than returning: 2.341 against
2.406 ms (ab_result_handoff_launch.json). Tried and not kept: a head woken by its work sleeping until a caller woken
by the same work had taken the interpreter lock (no gain: 2.50 against 2.51 ms); the frame copied into the
foundation's static input with one cudaMemcpyAsync instead of its one-copy graph's launch (2.341 against 2.336 ms);
the depth head's stream above seg's: the device trace shows depth's next kernel still waiting about 66 us behind
seg's upsample + argmax kernel either way (profile_steps_trace_depth_first.json.gz), and neither that priority nor
seg's kernel in 256-thread blocks instead of 64 (a wider block of depth's then fits where one of seg's ends) changed
the frame: 2.280, 2.278, 2.282 and 2.283 ms (ab_result_handoff_seg_block{128,512}.json).

Note [Inline launch]
~~~~~~~~~~~~~~~~~~~~
The frame's own hop, from the submitting thread to the foundation model, costs a wake-up too: on an H100 the
foundation thread began its run 0.14 ms after the frame was published, while the GPU idled. In thread mode, when
the foundation model runs from graphs bound to the slots (``runtime.inline_launch: auto``), its worker does not
wait for frames in the ring when it is ready for one: it acquires its output slot and *arms* the input ring's
``InlineLaunch`` with it. The thread that publishes the next frame (``Engine.submit`` or a
``frame_slot`` closing) then queues the foundation's work itself, on the foundation's stream (three graph
launches), *before* it publishes the frame: the slot is still its writer's, so no one else can see it, let alone
reuse it. It then publishes the frame already pinned for the foundation's reader (``publish_pinned``, one
critical section, the read counted as any other) and hands the pinned slots to the worker, which wakes, publishes
the features (Note [Event hand-off]) and does the rest of its run as usual: counting, waiting for its work,
releasing the frame. Nothing else changes hands: the worker alone decides when it is ready (rate limit, pause), a
launch that raises is raised in the worker (restart rules), and a frame published while the worker is not armed is
taken from the ring by the worker, as before. Arming, disarming, taking a frame from the ring and the inline launch
all happen under the offer's lock, so each frame is taken exactly once. The worker arms only while it is unlimited
(a rate limit is decided on each frame's timestamp, which needs the frame: ``rate.py``) and, under the lock, takes
no frame if a rate has been set since; ``Engine.set_rate`` stores the rate and then takes the lock, so no frame
submitted after it returns runs under the old rate. Measured on the H100 (compiled depth + seg,
benchmarks/results/h100/profile_steps_inline.json): the first graph is queued 0.19 ms after the frame is published
instead of 0.29 ms, 3.44 instead of 3.52 ms a frame. The 0.14 ms that stayed between starting a run and the first
graph launch, in whichever thread launched, was the launch path's code running cold (Note [Launch path]). Queueing
the work before the frame is published, not after, took a further 0.05 ms off (H200, one engine, 14 rounds: 2.50
against 2.55 ms p50; 2.37 against 2.41 ms with ``wait_spin_us: 200``; ab_result_handoff_prelaunch_ab.json).

Note [Launch path]
~~~~~~~~~~~~~~~~~~
Host code runs several times slower right after its thread waited: on the H100 VM, entering a stream context and
inference mode and replaying a CUDA graph take 26 us in a loop and 141 us after the thread slept 3 ms (stream context
87 us, inference mode 21 us, the replay 32 us; benchmarks/results/h100/wakeups.json). Every run begins that way:
woken by its input, or in the thread that just submitted a frame. So a worker's loop (``run``) makes its stream
current and turns inference mode on once, for as long as it runs, and a run on the worker's own thread enters
neither. A launch from the submitting thread (Note [Inline launch]) cannot leave that thread on the worker's stream,
and switching there and back costs about 0.1 ms after a wait however it is done (wakeups_switch.json); so a
slot-bound executor launches its three graphs with ``cudaGraphLaunch`` straight onto the worker's stream
(``run_bound_on``; CUDA Python bindings), which needs no switch and no inference mode, and switches streams only
where it cannot (no bindings, another device current, a graph that draws random numbers). Measured on the H100,
compiled depth + seg from a frame slot, 300 frames: the foundation's first graph is queued 0.12 ms after the frame is
published (0.18 ms with the stream switched, 0.2 ms before this Note), and a frame takes 3.38 ms p50 against 3.55
ms with the worker launching (profile_steps_launch_path.json).
"""

from __future__ import annotations

import logging
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
from vpengine.runtime.control import PAUSED, RUNNING, ControlBlock, ControlDesc
from vpengine.runtime.device import DeviceContext
from vpengine.runtime.rate import RateGate
from vpengine.specs import SpecDict
from vpengine.transport.ring import RingDesc, RingWriter, SlotInfo, SlotRing

log = logging.getLogger("vpengine.worker")


@dataclass(frozen=True)
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
        poll_s: float = 0.5,
        bound: bool = False,
    ) -> None:
        self.spec = spec
        self.name = spec.name
        self.model = model
        self.output_spec = output_spec
        self.reader = in_ring.reader(spec.in_reader)
        self.writer = out_ring.writer()
        self.control = control
        self.dev = device
        self.poll_s = poll_s
        self.gate = RateGate()
        self._checked = False
        self._should_stop: Callable[[], bool] = lambda: False
        self._keys = input_keys(spec, in_ring)
        self._in_ring = in_ring
        # Note [Event hand-off]: this worker publishes queued work with one event per output slot.
        self._handoff: list[Any] | None = out_ring.device_events
        # Note [Inline launch]: the submitting thread may queue this (foundation) worker's work; set by prepare_worker
        self._inline: InlineLaunch | None = None
        self._thread: int | None = None  # the thread running the loop (Note [Launch path])
        self._spare: SlotInfo | None = None  # the output slot an armed worker offers
        # The executor runs straight from the slots (Note [Slot-bound runs]): no staging, no copies here.
        self._bound = bound
        # Inputs live wherever their ring lives; a model on another device reads preallocated staging copies.
        self._staging: dict[str, torch.Tensor] | None = None
        if not bound and in_ring.data_region.device != device.device:
            self._staging = {
                k: torch.empty_like(in_ring.views[0][k], device=device.device) for k in self._keys
            }

    def _inputs(self, slot: SlotInfo) -> dict[str, torch.Tensor]:
        if self._staging is None:
            return {k: slot.tensors[k] for k in self._keys}
        for k, t in self._staging.items():
            t.copy_(slot.tensors[k], non_blocking=True)
        return self._staging

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
            self._drop_spare()

    def _loop(self, should_stop: Callable[[], bool]) -> None:
        ctl, name = self.control, self.name
        while not should_stop():
            ctl.heartbeat(name)
            rate = ctl.rate(name)
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

    def _admit(self, slot: SlotInfo, rate: float | None) -> bool:
        """Whether the frame in ``slot`` runs, by the rate gate on the frame's own timestamp (``rate.py``); frames
        this model never saw (it was busy) and a frame the gate holds back are counted skipped, and a held-back
        frame is answered (Note [Answered frames]). A rate set while this worker waited for the frame (a pause,
        say) decides: ``Engine.set_rate`` stores the rate before it returns, and a frame published after that is
        seen only after the store, so a pause stops every frame submitted after it."""
        now_rate = self.control.rate(self.name)
        if now_rate != rate:
            self.gate.update(now_rate)
        if self.gate.admit(slot.t_capture, slot.t_submit, slot.missed):
            if slot.missed:
                self.control.add(self.name, "skipped", slot.missed)
            return True
        self.control.add(self.name, "skipped", 1 + slot.missed)
        self.control.decide(self.name, slot.origin, ran=False)
        return False

    def _step(self, slot: SlotInfo, out: SlotInfo | None = None) -> None:
        """One run on a pinned, admitted ``slot``, into ``out`` (an output slot already acquired) or one it
        acquires. A run that publishes nothing (no output slot, or the model raised) still answers the frame."""
        t_start = time.monotonic()
        ran = False
        try:
            if out is None:
                out = self.writer.acquire(timeout=None, should_stop=self._should_stop)
            if out is None:
                self.control.add(self.name, "dropped")
                return
            self._launch(slot, out)
            self._finish(slot, out, t_start)
            ran = True
        finally:
            if not ran:
                self.control.decide(self.name, slot.origin, ran=False)

    def _launch(self, slot: SlotInfo, out: SlotInfo) -> None:
        """Queue the model's work from ``slot`` into ``out`` (on the CPU: do it). Gives ``out`` back if that raises.
        Called by this worker's thread, or by the submitting thread (Note [Inline launch])."""
        # read each frame: a head can start before the foundation thread has given the ring its events
        events = self._in_ring.device_events
        if events is not None:  # the slot's writer published it queued: read it only after that work
            self.dev.wait_on(events[slot.index])
        try:
            if threading.get_ident() == self._thread:  # run() made the stream current, inference mode on
                self._run_model(slot, out)
            elif self._bound:  # graph launches dispatch no tensor ops: no inference mode needed
                self.model.run_bound_on(self.dev.stream, slot.index, out.index)  # type: ignore[attr-defined]
            else:
                with self.dev.active(), torch.inference_mode():
                    self._run_model(slot, out)
            if self._handoff is not None:
                self.dev.mark(self._handoff[out.index])
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
            t.copy_(outputs[k], non_blocking=True)

    def _finish(self, slot: SlotInfo, out: SlotInfo, t_start: float) -> None:
        """Count and publish a run whose work ``_launch`` queued; the caller then releases ``slot``."""
        ctl, name = self.control, self.name
        handoff = self._handoff
        if handoff is None:
            try:
                self.dev.complete()  # Note [Device sync]: publish only what is complete
            except BaseException:
                self.writer.abort(out)
                raise
        # Counters first, then publish: whoever sees the output also sees it counted.
        t_end = time.monotonic()
        ctl.record_run(name, t_start, t_end - t_start, t_end - slot.t_submit, slot.frame_id)
        self.writer.publish(out, slot.frame_id, slot.t_capture, slot.t_submit, slot.origin)
        ctl.decide(name, slot.origin, ran=True, wake=self.spec.notify_output)
        if handoff is not None:
            # The input slot is released (by run) only after the work that read it is done; the run's times
            # are the device's, not the queueing's.
            self.dev.complete()
            t_end = time.monotonic()
            ctl.amend_last_run(name, t_end - t_start, t_end - slot.t_submit)
            if self.spec.notify_output:
                # Note [Result hand-off]: when it was there; wakes readers waiting for done results
                self.writer.ring.mark_done(out, t_end)
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
                offer.arm(self, self._spare, None)
                try:
                    offer.cond.wait(self.poll_s)
                finally:
                    offer.disarm(self)
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
                self.control.add(self.name, "skipped", slot.missed)
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


class InlineLaunch:
    """Note [Inline launch]: the input ring's offer from a ready foundation worker to the thread that publishes the
    next frame. One per input ring object (thread mode), kept across restarts of the worker."""

    def __init__(self) -> None:
        self.cond = threading.Condition(threading.Lock())
        self._core: WorkerCore | None = None
        self._out: SlotInfo | None = None
        self._done: tuple[SlotInfo, float, BaseException | None] | None = None
        self._rate: float | None = None
        self.launches = 0  # frames launched by submitting threads

    # worker side, holding cond
    def arm(self, core: WorkerCore, out: SlotInfo, rate: float | None) -> None:
        """Offer ``core``'s output slot ``out`` to the next frame's publisher; ``rate`` is the rate its gate opened
        under (read then, not now: a pause set in between must stop the launch)."""
        self._core, self._out = core, out
        self._rate = rate

    def disarm(self, core: WorkerCore) -> None:
        if self._core is core:
            self._core = self._out = None

    def take_done(self) -> tuple[SlotInfo, float, BaseException | None] | None:
        done, self._done = self._done, None
        return done

    # submitting side
    def publish(
        self, writer: RingWriter, slot: SlotInfo, frame_id: int, t_capture: float, t_submit: float
    ) -> int:
        """Publish the frame filled in ``slot`` (the input ring's ``writer`` holds it); if a worker is armed, queue
        its work on the frame first, then publish the frame pinned for its reader and hand it over. The frame's seq.
        """
        with self.cond:
            core, out = self._core, self._out
            if core is None or out is None or core.control.rate(core.name) != self._rate:
                # no worker armed, or the rate changed since (a pause, say): the worker's gate decides, once woken
                return writer.publish(slot, frame_id, t_capture, t_submit)
            self._core = self._out = None
            t_start = time.monotonic()
            error: BaseException | None = None
            try:  # queued before the frame is published: nobody else can see the slot yet, let alone reuse it
                core._launch(slot, out)
            except Exception as e:  # raised in the worker, under its restart rules; never in submit
                error = e
            pinned = writer.publish_pinned(slot, frame_id, t_capture, t_submit, core.reader)
            self._done = (pinned, t_start, error)
            self.launches += 1
            self.cond.notify_all()
            return pinned.seq

    def wake(self) -> None:
        """Wake an armed worker (at stop), which then disarms."""
        with self.cond:
            self.cond.notify_all()


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
    spec: WorkerSpec, in_ring: SlotRing, out_ring: SlotRing, control: ControlBlock, own_process: bool
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
    dev = DeviceContext(device, mcfg.stream_priority, cfg.runtime.sync_spin_us * 1e-6)
    control.set(spec.name, "stream_priority", dev.priority)
    if dev.cuda:
        _register_host_rings(in_ring, out_ring)
        from vpengine.transport.cuda_vmm import mps_enabled

        try:
            control.set(spec.name, "mps_active", int(mps_enabled(device.index or 0)))
        except Exception:  # the bindings are optional in thread mode; MPS status is informational
            control.set(spec.name, "mps_active", 0)
    with dev.active():
        model = build_model(
            cfg, spec.name, spec.role, spec.upstream, spec.upstream_meta, device, plan_only=False
        )
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
                cache_dir=cfg.weights.cache_dir,
            )
            # Warm-up on random inputs: first-run allocations, autotuning and compilation all happen before READY,
            # so the steady state allocates nothing (Invariant: constant memory).
            with torch.inference_mode():
                check_outputs(spec.name, model.output_spec, executor(model.example_inputs(device)))
                keys = input_keys(spec, in_ring)
                bound = executor.bind([{k: v[k] for k in keys} for v in in_ring.views], list(out_ring.views))
        dev.complete()
    # Note [Event hand-off]: every reader of the features is a head thread of this process on this device. A
    # restarted model keeps the events: a slot its predecessor published is still ordered by them.
    if dev.cuda and not own_process and out_ring.device_events is None:
        if spec.role == "foundation" and cfg.runtime.feature_handoff == "event":
            out_ring.device_events = [torch.cuda.Event() for _ in range(out_ring.n_slots)]
        elif spec.role == "head" and cfg.runtime.result_handoff == "event":
            # Note [Result hand-off]: read on the host by the engine, which sleeps in the driver on them, or polls
            # them at the end of each wait (runtime.wait_spin_us > 0)
            out_ring.device_events = [torch.cuda.Event(blocking=True) for _ in range(out_ring.n_slots)]
    control.set(spec.name, "device_mem_bytes", dev.memory_bytes())
    control.set(spec.name, "started_at", time.monotonic())
    core = WorkerCore(
        spec, executor, model.output_spec, in_ring, out_ring, control, dev, cfg.runtime.poll_s, bound=bound
    )
    inline = cfg.runtime.inline_launch
    if (
        spec.role == "foundation"
        and not own_process
        and (inline == "always" or (inline == "auto" and dev.cuda and bound))
    ):
        if in_ring.inline is None:  # Note [Inline launch]
            in_ring.inline = InlineLaunch()
        core._inline = in_ring.inline
    control.heartbeat(spec.name)
    control.set_state(spec.name, READY)
    return core
