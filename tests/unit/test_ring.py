"""Slot ring semantics in one process: LatestBuffer and FifoQueue behaviour, pins, overflow policies, accounting."""

from __future__ import annotations

import itertools
import threading
import time

import pytest
import torch

from vpengine.specs import TensorSpec
from vpengine.transport import ReaderDecl, SlotLayout, SlotRing, fifo_queue, latest_buffer
from vpengine.transport.layout import ALIGN

SPECS = {"x": TensorSpec((4, 4), "float32"), "n": TensorSpec((), "int64"), "tiny": TensorSpec((3,), "uint8")}


def write(ring: SlotRing, value: int, frame_id: int | None = None) -> int | None:
    w = ring.writer()
    slot = w.acquire(timeout=0)
    if slot is None:
        return None
    slot.tensors["x"].fill_(value)
    slot.tensors["n"].fill_(value)
    return w.publish(slot, value if frame_id is None else frame_id, float(value), time.monotonic())


def test_latest_reader_gets_newest_and_counts_what_it_missed():
    ring = latest_buffer("t", SPECS, ["a", "b"])
    try:
        for v in range(1, 6):
            write(ring, v)
        a = ring.reader("a")
        s = a.pin()
        assert (s.seq, s.frame_id, s.missed) == (5, 5, 4)
        assert s.tensors["x"][0, 0].item() == 5
        a.release(s)
        assert a.pin() is None  # nothing newer than what it saw
        write(ring, 6)
        s = a.pin()
        assert (s.seq, s.missed) == (6, 0)
        a.release(s)
        st = ring.stats()["readers"]
        assert st["a"] == {"active": True, "reads": 2, "missed": 4, "pending": 0, "pinned": False}
        assert st["b"]["pending"] == 6 and st["b"]["reads"] == 0  # b has not looked yet
    finally:
        ring.close()


def test_fifo_reads_in_order_and_drop_oldest_counts_exactly():
    ring = fifo_queue("t", SPECS, ["r"], n_slots=4)
    try:
        for v in range(1, 7):  # 6 writes into 4 slots, nobody reading: 2 overwritten
            assert write(ring, v) is not None
        r = ring.reader("r")
        got = []
        while (s := r.pin()) is not None:
            got.append((s.seq, s.missed, int(s.tensors["n"])))
            r.release(s)
        assert got == [(3, 2, 3), (4, 0, 4), (5, 0, 5), (6, 0, 6)]
        st = ring.stats()["readers"]["r"]
        assert st["reads"] + st["missed"] == 6 and st["missed"] == 2
    finally:
        ring.close()


def test_fifo_drop_newest_refuses_and_counts():
    ring = fifo_queue("t", SPECS, ["r"], n_slots=3, overflow="drop_newest")
    try:
        assert [write(ring, v) for v in (1, 2, 3)] == [1, 2, 3]
        assert write(ring, 4) is None and write(ring, 5) is None
        assert ring.stats()["dropped_newest"] == 2
        r = ring.reader("r")
        s = r.pin()
        assert (s.seq, s.missed) == (1, 0)
        r.release(s)
        assert write(ring, 6) == 4  # one slot read, so one more fits
        seqs = []
        while (s := r.pin()) is not None:
            seqs.append(int(s.tensors["n"]))
            r.release(s)
        assert seqs == [2, 3, 6]
        assert ring.stats()["readers"]["r"]["missed"] == 0  # refused items were never published
    finally:
        ring.close()


def test_fifo_block_waits_for_the_reader():
    ring = fifo_queue("t", SPECS, ["r"], n_slots=3, overflow="block")
    try:
        for v in (1, 2, 3):
            write(ring, v)
        w = ring.writer()
        assert w.acquire(timeout=0.05) is None  # full: it waited and timed out
        got = {}

        def blocked_writer():
            t = time.monotonic()
            got["slot"] = w.acquire(timeout=5.0)
            got["waited"] = time.monotonic() - t

        th = threading.Thread(target=blocked_writer)
        th.start()
        time.sleep(0.2)
        assert th.is_alive()
        r = ring.reader("r")
        s = r.pin()
        r.release(s)
        th.join(2)
        assert got["slot"] is not None and 0.15 < got["waited"] < 1.0
    finally:
        ring.close()


def test_pinned_slot_is_never_overwritten():
    ring = latest_buffer("t", SPECS, ["a", "b"])  # 4 slots
    try:
        write(ring, 1)
        a = ring.reader("a")
        s = a.pin()
        for v in range(2, 40):
            write(ring, v)
            assert s.tensors["x"].eq(1).all()  # content intact while pinned
            assert ring.pins()["a"] == s.index
        a.release(s)
        s2 = a.pin()
        assert s2.seq == 39 and s2.missed == 37
        a.release(s2)
    finally:
        ring.close()


def test_pin_slot_takes_over_another_readers_pin_and_keeps_it():
    ring = latest_buffer("t", SPECS, ["a", "lease"])  # 4 slots
    try:
        write(ring, 1)
        a, lease = ring.reader("a"), ring.reader("lease")
        s = a.pin()
        held = lease.pin_slot(s)
        assert (held.index, held.seq) == (s.index, s.seq)
        a.release(s)  # the lease still pins it
        for v in range(2, 20):
            write(ring, v)
            assert held.tensors["x"].eq(1).all() and ring.pins()["lease"] == held.index
        with pytest.raises(RuntimeError, match="already pins a slot"):
            lease.pin_slot(s)
        lease.release(held)
        for v in range(20, 26):  # now the slot is reused
            write(ring, v)
        assert lease.pin_slot(s) is None  # it no longer holds what s described: nothing pinned
        assert ring.pins()["lease"] == -1
    finally:
        ring.close()


def test_writer_never_waits_with_readers_plus_two_slots():
    readers = ["a", "b", "c"]
    ring = latest_buffer("t", SPECS, readers)  # 5 slots
    try:
        handles = [ring.reader(r) for r in readers]
        pinned: dict[str, object] = {}
        for v in range(1, 300):
            slot = ring.writer().acquire(timeout=0)  # must never need to wait
            assert slot is not None, f"writer had to wait at write {v}"
            held = {p.index for p in pinned.values()}  # type: ignore[attr-defined]
            assert slot.index not in held
            ring.writer().publish(slot, v, 0.0, 0.0)
            r = handles[v % 3]  # readers take turns re-pinning the newest: worst case for the writer
            if r.name in pinned:
                r.release(pinned.pop(r.name))
            pinned[r.name] = r.pin()
    finally:
        ring.close()


def test_too_few_slots_is_a_clear_error():
    with pytest.raises(ValueError, match=r"n_slots=3 is too small for 2 readers and 1 tags; need at least 4"):
        SlotRing.create("t", SPECS, 3, [ReaderDecl("a"), ReaderDecl("b")])
    with pytest.raises(ValueError, match="unknown overflow policy 'spill'"):
        SlotRing.create("t", SPECS, 3, [ReaderDecl("a")], overflow="spill")  # type: ignore[arg-type]


def test_reader_holds_one_pin_and_release_checks_the_slot():
    ring = latest_buffer("t", SPECS, ["a"])
    try:
        write(ring, 1)
        a = ring.reader("a")
        s = a.pin()
        write(ring, 2)
        with pytest.raises(RuntimeError, match="already pins"):
            a.pin()
        other = type(s)(index=(s.index + 1) % ring.n_slots, tensors={})
        with pytest.raises(RuntimeError, match="does not pin slot"):
            a.release(other)
        a.release(s)
    finally:
        ring.close()


def test_peek_returns_newest_even_if_seen_and_counts_nothing():
    ring = latest_buffer("t", SPECS, ["a"])
    try:
        assert ring.reader("a").pin(peek=True) is None
        write(ring, 1)
        write(ring, 2)
        a = ring.reader("a")
        for _ in range(3):
            s = a.pin(peek=True)
            assert s.seq == 2
            a.release(s)
        assert ring.stats()["readers"]["a"]["reads"] == 0
    finally:
        ring.close()


def test_origin_carries_frame_identity_and_pin_origin_finds_it():
    src = latest_buffer("in", SPECS, ["fm"])
    dst = latest_buffer("out", SPECS, ["peek"])
    try:
        for v in range(1, 4):
            write(src, v, frame_id=100 + v)
        fm = src.reader("fm")
        s = fm.pin()
        assert (s.origin, s.frame_id) == (3, 103)  # input ring: origin is its own seq
        w = dst.writer()
        o = w.acquire()
        w.publish(o, s.frame_id, s.t_capture, s.t_submit, s.origin)
        fm.release(s)
        peek = dst.reader("peek")
        slot, newest = peek.pin_origin(3)
        assert slot is not None and slot.frame_id == 103 and newest == 3
        peek.release(slot)
        slot, newest = peek.pin_origin(2)  # origin 2 was skipped: the newest is past it
        assert slot is None and newest == 3
    finally:
        src.close()
        dst.close()


def test_pin_origin_reads_newest_among_the_frames_camera_only():
    ring = SlotRing.create("out", SPECS, 5, [ReaderDecl("peek")], n_tags=2)
    try:
        w = ring.writer()
        for origin, tag in ((1, 1), (3, 0)):  # rear's frame 1 waits for its output; front's frame 3 is out
            w.publish(w.acquire(), origin, 0.0, 0.0, origin, tag=tag)
        peek = ring.reader("peek")
        slot, newest = peek.pin_origin(2, tag=1)  # rear's frame 2: not out yet, and not passed by rear's frames
        assert slot is None and newest == 1
        slot, newest = peek.pin_origin(2)  # every camera's: front's frame 3 is past it
        assert slot is None and newest == 3
    finally:
        ring.close()


def test_release_reader_and_reset_writer_repair_a_dead_process():
    ring = latest_buffer("t", SPECS, ["a"])  # 3 slots
    try:
        write(ring, 1)
        a = ring.reader("a")
        a.pin()  # "dies" holding the pin
        half = ring.writer().acquire()  # writer "dies" mid-write
        assert half is not None
        assert ring.release_reader("a") == 1  # the origin of the slot it held
        assert ring.release_reader("a") is None
        assert ring.reset_writer() == 1
        assert ring.pins()["a"] == -1
        for v in range(2, 10):  # everything usable again
            assert write(ring, v) is not None
        s = a.pin()
        assert s.seq == 9
        a.release(s)
    finally:
        ring.close()


def test_abort_gives_the_slot_back_unpublished():
    ring = latest_buffer("t", SPECS, ["a"])
    try:
        w = ring.writer()
        s = w.acquire()
        w.abort(s)
        assert ring.reader("a").pin() is None
        assert ring.stats()["published"] == 0
    finally:
        ring.close()


def test_wait_sleeps_until_publish_without_spinning():
    ring = latest_buffer("t", SPECS, ["a"])
    try:
        a = ring.reader("a")
        t0 = time.monotonic()
        threading.Timer(0.2, lambda: write(ring, 1)).start()
        cpu0 = time.process_time()
        s = a.pin(timeout=5.0)
        cpu = time.process_time() - cpu0
        waited = time.monotonic() - t0
        assert s is not None and 0.15 < waited < 1.0
        assert cpu < 0.05, f"waiting burned {cpu:.3f} s of CPU"
        a.release(s)
        assert a.pin(timeout=0.1) is None  # times out when nothing comes
    finally:
        ring.close()


def test_inactive_reader_counts_from_activation():
    ring = SlotRing.create("t", SPECS, 4, [ReaderDecl("res", "fifo", active=False), ReaderDecl("peek")])
    try:
        for v in range(1, 4):
            write(ring, v)
        res = ring.reader("res")
        assert ring.stats()["readers"]["res"]["pending"] == 0  # inactive: nothing owed
        res.activate(from_now=True)
        assert res.pin() is None  # earlier items are not part of its stream
        write(ring, 4)
        s = res.pin()
        assert (s.seq, s.missed) == (4, 0)
        res.release(s)
    finally:
        ring.close()


def test_layout_is_one_allocation_with_aligned_non_overlapping_views():
    specs = {
        "a": TensorSpec((1, 1369, 384), "float32"),
        "cls": TensorSpec((1, 384), "float32"),
        "count": TensorSpec((), "int32"),
        "img": TensorSpec((7, 5, 3), "uint8"),
    }
    layout = SlotLayout.from_specs(specs, 4)
    flat = torch.zeros(layout.total_bytes, dtype=torch.uint8)
    views = layout.views(flat)
    spans = []
    for slot in views:
        for k, t in slot.items():
            assert t.untyped_storage().data_ptr() == flat.untyped_storage().data_ptr()  # one allocation
            off = t.data_ptr() - flat.data_ptr()
            assert off % ALIGN == 0
            assert tuple(t.shape) == specs[k].shape and t.dtype == specs[k].torch_dtype
            spans.append((off, off + specs[k].nbytes))
    spans.sort()
    assert all(a[1] <= b[0] for a, b in itertools.pairwise(spans))  # no overlap
    # tiny tensors share the slot: far less than one 2 MiB page per tensor
    assert layout.slot_bytes < 1369 * 384 * 4 + 384 * 4 + 3 * ALIGN + 105


def test_publish_can_pin_the_new_slot_for_a_reader_counting_the_read_as_a_pin_would():
    ring = latest_buffer("t", SPECS, ["a", "b"])
    try:
        write(ring, 1)  # a never saw this one: counted missed when it gets the next
        w, a = ring.writer(), ring.reader("a")
        slot = w.acquire(timeout=0)
        slot.tensors["n"].fill_(2)
        pinned = w.publish_pinned(slot, 2, 0.0, time.monotonic(), a)
        seq = slot.seq
        assert (pinned.index, pinned.seq, pinned.frame_id, pinned.missed) == (slot.index, seq, 2, 1)
        assert ring.pins()["a"] == slot.index and a.cursor == seq
        assert not a.available()  # nothing unseen: the publish's pin was this reader's read
        st = ring.stats()["readers"]["a"]
        assert (st["reads"], st["missed"]) == (1, 1)
        b = ring.reader("b")
        got = b.pin()
        assert got is not None and got.seq == seq  # other readers see it as usual
        b.release(got)
        slot2 = w.acquire(timeout=0)
        assert slot2.index != slot.index  # pinned by a: not reused
        with pytest.raises(RuntimeError, match="already pins"):
            w.publish_pinned(slot2, 3, 0.0, time.monotonic(), a)
        a.release(pinned)
    finally:
        ring.close()


# ------------------------------------------------------------------------------ Note [Tagged slots]: cameras
def publish_tagged(ring: SlotRing, value: float, tag: int) -> int:
    w = ring.writer()
    slot = w.acquire(timeout=0)
    assert slot is not None
    slot.tensors["x"].fill_(value)
    return w.publish(slot, int(value), 0.0, 0.0, tag=tag)


def test_a_tagged_reader_sees_only_its_cameras_frames_and_counts_in_their_own_sequence():
    ring = SlotRing.create(
        "in", SPECS, 6, [ReaderDecl("fm@front", tag=0), ReaderDecl("fm@rear", tag=1), ReaderDecl("all")], n_tags=2
    )
    try:
        front, rear, every = (ring.reader(n) for n in ("fm@front", "fm@rear", "all"))
        publish_tagged(ring, 1.0, 0)
        publish_tagged(ring, 2.0, 1)
        publish_tagged(ring, 3.0, 0)  # front's second frame: front missed one of its own, not rear's
        s = front.pin()
        assert s is not None and s.tensors["x"][0, 0].item() == 3.0 and s.tag == 0 and s.tag_seq == 2
        assert s.missed == 1
        r = rear.pin()
        assert r is not None and r.tensors["x"][0, 0].item() == 2.0 and r.missed == 0  # one reader each: both pinned
        a = every.pin()
        assert a is not None and a.tensors["x"][0, 0].item() == 3.0 and a.missed == 2  # untagged: every slot
        for reader, slot in ((front, s), (rear, r), (every, a)):
            reader.release(slot)
        assert front.pin() is None  # nothing newer of its own
        st = ring.stats()["readers"]
        assert st["fm@front"]["missed"] == 1 and st["fm@rear"]["missed"] == 0 and st["fm@front"]["pending"] == 0
    finally:
        ring.close()


def test_the_writer_keeps_each_cameras_newest_frame_for_its_reader():
    # a busy camera must not push a quiet camera's newest frame out before its reader looked
    ring = SlotRing.create("in", SPECS, 5, [ReaderDecl("fm@a", tag=0), ReaderDecl("fm@b", tag=1)], n_tags=2)
    try:
        publish_tagged(ring, 100.0, 1)  # camera b: one frame
        for i in range(10):  # camera a: many
            publish_tagged(ring, float(i), 0)
        b = ring.reader("fm@b").pin()
        assert b is not None and b.tensors["x"][0, 0].item() == 100.0
        a = ring.reader("fm@a").pin()
        assert a is not None and a.tensors["x"][0, 0].item() == 9.0 and a.missed == 9
    finally:
        ring.close()


def test_a_camera_that_publishes_more_overwrites_its_own_older_slots_not_another_cameras():
    # an output ring read by origin (Engine.wait): a camera whose outputs come faster, or whose caller keeps up, must
    # not push out the outputs a slower camera's caller has not waited for yet (Note [Tagged slots])
    ring = SlotRing.create("out", SPECS, 7, [ReaderDecl("peek")], n_tags=2)
    try:
        slow = [publish_tagged(ring, 100.0 + i, 1) for i in range(3)]
        fast = [publish_tagged(ring, float(i), 0) for i in range(10)]
        peek = ring.reader("peek")
        for origin in slow:  # all three kept: camera 0 held the most, so it gave up its own
            slot, _ = peek.pin_origin(origin)
            assert slot is not None and slot.tag == 1
            peek.release(slot)
        kept = [o for o in fast if (s := peek.pin_origin(o)[0]) is not None and peek.release(s) is None]
        assert kept == fast[-4:]  # the rest of the ring, its newest
    finally:
        ring.close()


def test_slots_lent_out_do_not_count_against_their_cameras_share():
    # an output ring as the engine sizes it: 2 cameras, 2 slots a camera, 2 leases, the newest of each; two results
    # of camera 0 lent out (pinned by lease readers) must not make it the camera that gives up its slots
    readers = [ReaderDecl("peek"), ReaderDecl("lease0", active=False), ReaderDecl("lease1", active=False)]
    ring = SlotRing.create("out", SPECS, 2 * 2 + 2 + 1, readers, n_tags=2)
    try:
        lent = [publish_tagged(ring, float(i), 0) for i in range(2)]
        leases = [ring.reader(f"lease{i}") for i in range(2)]
        pins = [lease.pin_origin(o)[0] for lease, o in zip(leases, lent)]
        assert all(p is not None for p in pins)
        for i in range(6):  # the cameras take turns
            publish_tagged(ring, 10.0 + i, 0)
            publish_tagged(ring, 100.0 + i, 1)
        tags = [ring.slot_tag(i) for i in range(ring.n_slots) if i not in {p.index for p in pins}]
        assert sorted(tags) == [0, 0, 1, 1, 1]  # beside the two lent: 2 of camera 0 (its share), 3 of camera 1
        for lease, p in zip(leases, pins):
            lease.release(p)
    finally:
        ring.close()


def test_a_tagged_fifo_reader_under_block_is_never_overwritten_by_another_cameras_frames():
    ring = SlotRing.create(
        "in", SPECS, 5, [ReaderDecl("fm@a", "fifo", tag=0), ReaderDecl("fm@b", "fifo", tag=1)], "cpu", n_tags=2,
        overflow="drop_newest",
    )  # fmt: skip
    try:
        publish_tagged(ring, 1.0, 0)
        publish_tagged(ring, 2.0, 0)
        publish_tagged(ring, 3.0, 1)
        got = []
        reader = ring.reader("fm@a")
        while (s := reader.pin()) is not None:
            got.append(s.tensors["x"][0, 0].item())
            reader.release(s)
        assert got == [1.0, 2.0]  # in order, none lost to camera b's frame
    finally:
        ring.close()


def test_tags_out_of_range_are_refused():
    with pytest.raises(ValueError, match=r"readers with a tag out of range: \['x'\]"):
        SlotRing.create("t", SPECS, 6, [ReaderDecl("x", tag=2)], n_tags=2)
    ring = SlotRing.create("t", SPECS, 4, [ReaderDecl("x")], n_tags=2)
    try:
        with pytest.raises(ValueError, match="has 2 tags; got tag 5"):
            publish_tagged(ring, 1.0, 5)
    finally:
        ring.close()
