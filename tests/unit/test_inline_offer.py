"""Note [Inline launch], the offer alone: what ``InlineLaunch.publish`` does for the thread that publishes a frame,
with a stand-in worker, and the worker's side of it on real rings (the engine-level behaviour is in
tests/integration/test_inline_launch.py)."""

from __future__ import annotations

import time
from types import SimpleNamespace

import torch

from vpengine.config import load_config
from vpengine.runtime.control import ControlBlock
from vpengine.runtime.device import DeviceContext
from vpengine.runtime.handoff import InlineLaunch, WorkerHandoff
from vpengine.runtime.lanes import make_lanes
from vpengine.runtime.worker import WorkerCore, WorkerSpec
from vpengine.specs import TensorSpec
from vpengine.transport.ring import latest_buffer


class Control:
    def __init__(self) -> None:
        self.hz: float | None = None

    def rate(self, name: str) -> float | None:
        return self.hz


class Reader:
    name = "foundation"


class Slot:
    pass


class Writer:
    """The input ring's writer: records each publish, and whether it pinned the frame for a reader."""

    def __init__(self, log: list[str]) -> None:
        self.log, self.seq = log, 0

    def publish(self, slot, frame_id, t_capture, t_submit, tag=0) -> int:  # type: ignore[no-untyped-def]
        self.seq += 1
        self.log.append("publish")
        return self.seq

    def publish_pinned(self, slot, frame_id, t_capture, t_submit, reader, tag=0):  # type: ignore[no-untyped-def]
        self.seq += 1
        self.log.append(f"publish pinned for {reader.name}")
        self.pinned = SimpleNamespace(seq=self.seq)  # the reader's pin of the frame
        return self.pinned


class Worker:
    name = "foundation"

    def __init__(self, log: list[str], fail: bool = False) -> None:
        self.control, self.reader, self.fail, self.log = Control(), Reader(), fail, log
        self.launched: list[tuple[object, object]] = []

    def _launch(self, slot: object, out: object) -> None:
        self.log.append("launch")
        if self.fail:
            raise RuntimeError("launch failed")
        self.launched.append((slot, out))


def offer_worker(fail: bool = False) -> tuple[InlineLaunch, Worker, Writer, list[str]]:
    log: list[str] = []
    return InlineLaunch(), Worker(log, fail), Writer(log), log


def arm(offer: InlineLaunch, worker: Worker, out: object = "out") -> None:
    """What an unlimited foundation worker offers: its launch into ``out``, its reader, and its rate check."""
    offer.arm(lambda slot: worker._launch(slot, out), worker.reader, lambda: worker.control.hz is None)  # type: ignore[arg-type]


def publish(offer: InlineLaunch, writer: Writer, slot: Slot | None = None) -> int:
    return offer.publish(writer, slot or Slot(), 1, 0.0, 0.0)  # type: ignore[arg-type]


def test_nothing_is_launched_unless_a_worker_is_armed():
    offer, worker, writer, log = offer_worker()
    assert publish(offer, writer) == 1
    arm(offer, worker)
    offer.disarm()
    assert publish(offer, writer) == 2
    assert log == ["publish", "publish"] and offer.take_done() is None and offer.launches == 0


def test_an_armed_worker_gets_its_work_queued_before_the_frame_is_published_pinned_for_it_and_handed_over_once():
    offer, worker, writer, log = offer_worker()
    arm(offer, worker)
    slot = Slot()
    assert publish(offer, writer, slot) == 1
    assert log == ["launch", "publish pinned for foundation"]  # queued first: nobody can see the slot yet
    assert worker.launched == [(slot, "out")] and offer.launches == 1
    pinned, _, error = offer.take_done()  # type: ignore[misc]
    assert pinned is writer.pinned and error is None
    assert publish(offer, writer) == 2 and log[-1] == "publish"  # disarmed: the next frame waits for the worker
    assert offer.take_done() is None and offer.launches == 1


def test_a_rate_changed_since_arming_leaves_the_frame_to_the_worker():
    offer, worker, writer, log = offer_worker()
    arm(offer, worker)
    worker.control.hz = 0.0  # paused after it armed, before it woke to disarm
    publish(offer, writer)
    assert log == ["publish"] and worker.launched == []
    worker.control.hz = None  # the rate it armed under again
    publish(offer, writer)
    assert log[1:] == ["launch", "publish pinned for foundation"]


def test_the_rate_is_checked_when_the_frame_comes_not_when_the_worker_armed():
    offer, worker, writer, log = offer_worker()
    worker.control.hz = 0.0  # paused after the worker's loop read it unlimited, before it armed
    arm(offer, worker)
    publish(offer, writer)
    assert log == ["publish"] and worker.launched == []


def test_a_launch_that_raises_is_handed_to_the_worker_not_raised_in_submit():
    offer, worker, writer, log = offer_worker(fail=True)
    arm(offer, worker)
    assert publish(offer, writer) == 1  # no exception here, and the frame is published all the same
    pinned, _, error = offer.take_done()  # type: ignore[misc]
    assert log == ["launch", "publish pinned for foundation"]
    assert pinned is writer.pinned and isinstance(error, RuntimeError) and "launch failed" in str(error)


def foundation_core(poll_s: float, inline: bool = True) -> tuple[WorkerCore, ControlBlock]:
    """A foundation worker, with its input ring's offer if ``inline`` (thread mode), and one frame published."""
    x, f = {"x": TensorSpec((4,), "float32")}, {"f": TensorSpec((4,), "float32")}
    in_ring, out_ring = latest_buffer("input", x, ["foundation"]), latest_buffer("features", f, ["depth"])
    control = ControlBlock.create(["foundation"])
    spec = WorkerSpec(
        name="foundation",
        role="foundation",
        config={},
        upstream={},
        upstream_meta={},
        lanes=make_lanes(load_config({})).of("foundation"),
        in_ring=in_ring.desc,
        out_ring=out_ring.desc,
        notify_output=False,
    )
    core = WorkerCore(
        spec,
        lambda inputs: {"f": inputs["x"] * 2},
        f,
        in_ring,
        out_ring,
        control,
        DeviceContext("cpu"),
        poll_s,
        handoff=WorkerHandoff(inline=InlineLaunch() if inline else None),
    )
    w = in_ring.writer()
    slot = w.acquire(timeout=1.0)
    assert slot is not None
    slot.tensors["x"].fill_(1.0)
    w.publish(slot, 7, time.monotonic(), time.monotonic())
    return core, control


def test_a_worker_whose_rate_changed_after_its_gate_opened_takes_no_frame():
    """The race a CI run once hit: the gate opens unlimited, a pause is set, then the worker reaches the offer."""
    core, control = foundation_core(poll_s=5.0)
    control.set_rate("foundation", 0.0)
    t0 = time.monotonic()
    core._take_offered()
    assert time.monotonic() - t0 < 3.0  # back to its gate at once, not armed for poll_s (5 s)
    assert control.snapshot("foundation")["runs"] == 0 and core._inline.launches == 0  # type: ignore[union-attr]
    # the same call under the rate the gate saw finds the frame still there, and runs it
    control.set_rate("foundation", None)
    core._take_offered()
    assert control.snapshot("foundation")["runs"] == 1
    out = core.writer.ring.reader("depth").pin(timeout=0)
    assert out is not None and out.frame_id == 7 and torch.equal(out.tensors["f"], torch.full((4,), 2.0))


def test_a_pause_set_while_a_worker_waited_for_a_frame_holds_the_frame_back_and_counts_it():
    """Without the offer (process mode, or inline launch off) the worker waits in the ring; a pause set meanwhile
    stops the frame that then comes."""
    core, control = foundation_core(poll_s=5.0, inline=False)
    control.set_rate("foundation", 0.0)
    core._take_ring(core.lanes)  # its gate opened unlimited
    st = control.snapshot("foundation")
    assert st["runs"] == 0 and st["skipped"] == 1


def test_a_rate_raised_while_a_worker_waited_for_a_frame_runs_it():
    core, control = foundation_core(poll_s=5.0, inline=False)
    core.lanes[0].gate.update(10.0)  # its gate opened at 10 Hz
    control.set_rate("foundation", None)
    core._take_ring(core.lanes)
    st = control.snapshot("foundation")
    assert st["runs"] == 1 and st["skipped"] == 0
