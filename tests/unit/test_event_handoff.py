"""Note [Event hand-off]: the order of a worker's steps when the foundation hands its features to the heads with
a device event instead of a host wait. CUDA streams and events need a GPU (the engine's GPU tests run thread mode,
where the hand-off is on by default); here stand-ins record what the worker asked of them and when."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

import torch

from vpengine.config import load_config
from vpengine.runtime.control import ControlBlock
from vpengine.runtime.handoff import SlotEvents, WorkerHandoff
from vpengine.runtime.lanes import make_lanes
from vpengine.runtime.worker import WorkerCore, WorkerSpec
from vpengine.specs import TensorSpec
from vpengine.transport.ring import SlotRing, latest_buffer

X = {"x": TensorSpec((4,), "float32")}
F = {"f": TensorSpec((4,), "float32")}
D = {"d": TensorSpec((4,), "float32")}


class Event:
    def __init__(self, slot: int) -> None:
        self.slot = slot

    def query(self) -> bool:
        return False


def events(n: int) -> SlotEvents:
    """What the engine makes for a ring handed off on the device (runtime/handoff.py), with stand-in events."""
    made = iter(range(n))
    return SlotEvents(n, blocking=False, make_event=lambda blocking: Event(next(made)))


class Dev:
    """A stand-in DeviceContext: logs marks, waits and completions, and what the rings looked like at each."""

    device = torch.device("cpu")
    cuda = False  # no stream to move (Note [Stream priority at run time])

    def __init__(self, name: str, log: list[tuple], rings: dict[str, SlotRing], work_s: float = 0.0) -> None:
        self.name, self.log, self.rings, self.work_s = name, log, rings, work_s

    @contextlib.contextmanager
    def active(self) -> Iterator[None]:
        yield

    def wait_on(self, event: Event) -> None:
        self.log.append((self.name, "wait_on", event.slot))

    def mark(self, event: Event) -> None:
        self.log.append((self.name, "mark", event.slot))

    def complete(self) -> None:
        time.sleep(self.work_s)
        self.log.append(
            (
                self.name,
                "complete",
                self.rings["features"].last_seq,
                self.rings["input"].pins()["foundation"],
                self.rings["out"].last_seq,
                self.rings["features"].pins()["depth"],
            )
        )


def spec(name: str, role: str, in_ring: SlotRing, out_ring: SlotRing, upstream, notify: bool = False) -> WorkerSpec:  # type: ignore[no-untyped-def]
    config = {} if role == "foundation" else {"heads": [{"name": name, "model": "tiny_depth"}]}
    return WorkerSpec(
        name=name,
        role=role,  # type: ignore[arg-type]
        config=config,
        upstream=upstream,
        upstream_meta={},
        lanes=make_lanes(load_config(config)).of(name),
        in_ring=in_ring.desc,
        out_ring=out_ring.desc,
        notify_output=notify,
    )


def pipeline(handoff: bool, work_s: float = 0.0, results: bool = False):  # type: ignore[no-untyped-def]
    rings = {
        "input": latest_buffer("input", X, ["foundation"]),
        "features": latest_buffer("features", F, ["depth"]),
        "out": latest_buffer("out", D, ["results"]),
    }
    # what make_handoffs gives a thread-mode engine on CUDA: the features' events, a head's results' events
    features = events(rings["features"].n_slots) if handoff else None
    out = events(rings["out"].n_slots) if results else None
    control = ControlBlock.create(["foundation", "depth"])
    log: list[tuple] = []

    def foundation(inputs):  # type: ignore[no-untyped-def]
        log.append(("foundation", "model"))
        return {"f": inputs["x"] * 2}

    def depth(inputs):  # type: ignore[no-untyped-def]
        log.append(("depth", "model"))
        return {"d": inputs["f"] + 1}

    fm = WorkerCore(
        spec("foundation", "foundation", rings["input"], rings["features"], {}),
        foundation,
        F,
        rings["input"],
        rings["features"],
        control,
        Dev("foundation", log, rings, work_s),  # type: ignore[arg-type]
        handoff=WorkerHandoff(None, features),
    )
    head = WorkerCore(
        spec("depth", "head", rings["features"], rings["out"], F, notify=True),
        depth,
        D,
        rings["features"],
        rings["out"],
        control,
        Dev("depth", log, rings),  # type: ignore[arg-type]
        handoff=WorkerHandoff(features, out),
    )
    return rings, control, log, fm, head, {"features": features, "out": out}


def step(core: WorkerCore) -> None:
    slot = core.lanes[0].reader.pin(timeout=1.0)
    assert slot is not None
    try:
        core._run([slot])
    finally:
        core.lanes[0].reader.release(slot)


def submit(rings, i: int) -> None:  # type: ignore[no-untyped-def]
    w = rings["input"].writer()
    slot = w.acquire(timeout=1.0)
    slot.tensors["x"].fill_(float(i))
    w.publish(slot, i, time.monotonic(), time.monotonic())


def test_with_event_hand_off_features_are_published_before_the_foundation_waits_and_heads_wait_on_the_device():
    rings, control, log, fm, head, _ev = pipeline(handoff=True)
    for i in range(5):  # the rings rotate through their slots
        log.clear()
        submit(rings, i)
        step(fm)
        mark = [e for e in log if e[1] == "mark"]
        done = [e for e in log if e[1] == "complete"]
        assert len(mark) == 1 and len(done) == 1, log
        # the slot was marked, then published (features seq = i + 1) before the foundation waited for its work,
        # and the input slot was still pinned while it waited: the caller's frame is not reused under the read
        assert log.index(mark[0]) < log.index(done[0])
        assert done[0][2] == i + 1 and done[0][3] >= 0, done
        step(head)
        head_log = [e for e in log if e[0] == "depth"]
        # the head's stream waits on the very slot's event, before its model runs; its own output syncs on the host
        assert head_log[0] == ("depth", "wait_on", mark[0][2]), head_log
        assert head_log[1] == ("depth", "model") and head_log[2][1] == "complete", head_log
        out = rings["out"].reader("results")
        got = out.pin(timeout=1.0)
        assert got is not None and got.frame_id == i and torch.equal(got.tensors["d"], torch.full((4,), 2.0 * i + 1))
        out.release(got)
    assert control.snapshot("foundation")["runs"] == 5 and control.snapshot("depth")["runs"] == 5


def test_with_host_hand_off_the_foundation_publishes_only_completed_work_and_heads_do_not_wait_on_events():
    rings, _control, log, fm, head, _ev = pipeline(handoff=False)
    submit(rings, 0)
    step(fm)
    step(head)
    assert not [e for e in log if e[1] in ("mark", "wait_on")], log
    done = [e for e in log if e[0] == "foundation" and e[1] == "complete"]
    assert done[0][2] == 0, "published before its work was complete"


def test_a_handed_off_run_is_timed_by_its_device_work_not_by_its_queueing():
    rings, control, _log, fm, _head, _ev = pipeline(handoff=True, work_s=0.03)
    submit(rings, 0)
    step(fm)
    lat, e2e = control.recent_latencies("foundation")
    assert len(lat) == 1 and lat[0] >= 0.03 and e2e[0] >= lat[0], (lat, e2e)


def test_with_result_hand_off_a_head_publishes_before_its_work_is_done_and_marks_when_it_was():
    rings, control, log, fm, head, ev = pipeline(handoff=True, results=True)
    for i in range(4):
        log.clear()
        submit(rings, i)
        step(fm)
        word = control.output_word()
        t0 = time.monotonic()
        step(head)
        t1 = time.monotonic()
        head_log = [e for e in log if e[0] == "depth"]
        assert [e[1] for e in head_log] == ["wait_on", "model", "mark", "complete"], head_log
        # published (out seq = i + 1) before the head waited for its work, with the features still pinned: the
        # foundation cannot overwrite what the queued work reads
        assert head_log[-1][4] == i + 1 and head_log[-1][5] >= 0, head_log
        # the engine was woken twice, at publish and once the work was done, and knows when that was
        assert control.output_word() == (word + 2) & 0xFFFFFFFF
        slot = rings["out"].reader("results").pin(accept=ev["out"].done)
        assert slot is not None and slot.seq == i + 1
        seq, t_done = ev["out"].done_at[slot.index]
        assert seq == slot.seq and t0 <= t_done <= t1 and ev["out"].wait_done(slot) == t_done
        rings["out"].reader("results").release(slot)
    assert control.snapshot("depth")["runs"] == 4


def test_with_results_handed_off_on_the_host_a_head_publishes_only_completed_work():
    rings, control, log, fm, head, ev = pipeline(handoff=True, results=False)
    submit(rings, 0)
    step(fm)
    word = control.output_word()
    step(head)
    done = [e for e in log if e[0] == "depth" and e[1] == "complete"]
    assert done[0][4] == 0, "published before its work was complete"
    assert control.output_word() == (word + 1) & 0xFFFFFFFF
    assert ev["out"] is None  # nothing handed off: the head published completed work
