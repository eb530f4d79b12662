"""The single writer of a slot ring: which slot it takes (Note [Slot lifetime] and Note [Tagged slots] in ring.py),
how it overflows, and how a filled slot is published."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from vpengine.transport.ring_meta import (
    EMPTY,
    H_DROPPED_NEWEST,
    H_LAST_SEQ,
    H_PUBLISHED,
    H_WRITER_WAITING,
    MODE_CODE,
    OVERFLOW_CODE,
    PUBLISH_WORD_OFF,
    PUBLISHED,
    R_ACTIVE,
    R_CURSOR,
    R_MODE,
    R_PINNED,
    RELEASE_WORD_OFF,
    S_FRAME,
    S_ORIGIN,
    S_PID,
    S_SEQ,
    S_STATE,
    S_TAG,
    S_TAG_SEQ,
    S_TCAP,
    S_TPUB,
    S_TSUB,
    WRITING,
    SlotInfo,
)

if TYPE_CHECKING:
    from vpengine.transport.ring import SlotRing
    from vpengine.transport.ring_reader import RingReader


class RingWriter:
    """The single writer of a ring. ``acquire`` -> fill ``slot.tensors`` -> ``publish`` (or ``abort``)."""

    def __init__(self, ring: SlotRing) -> None:
        self.ring = ring

    def _choose(self) -> int | None:
        ring, q = self.ring, self.ring._q
        pinned = set()
        unread: dict[int | None, int] = {}  # tag (None: any) -> the oldest seq some FIFO reader has not read
        for r, decl in enumerate(ring.desc.readers):
            b = ring._reader(r)
            if q[b + R_PINNED] >= 0:
                pinned.add(q[b + R_PINNED])
            if ring._policy != 0 and q[b + R_ACTIVE] and q[b + R_MODE] == MODE_CODE["fifo"]:
                c = q[b + R_CURSOR]
                unread[decl.tag] = min(unread.get(decl.tag, c), c)
        newest: dict[int, int] = {}  # tag -> its newest published seq, kept for readers that have not looked yet
        held: dict[int, int] = {}  # tag -> how many published slots it has that no reader pins
        for i in range(ring.n_slots):
            b = ring._slot(i)
            if q[b + S_STATE] == PUBLISHED:
                t = q[b + S_TAG]
                newest[t] = max(newest.get(t, 0), q[b + S_SEQ])
                if i not in pinned:  # a slot a reader holds (a lent result) is not the camera's to give up
                    held[t] = held.get(t, 0) + 1
        # an empty slot first; else the oldest slot of the camera that holds the most (Note [Tagged slots])
        best, best_key = None, None
        for i in range(ring.n_slots):
            b = ring._slot(i)
            state, seq = q[b + S_STATE], q[b + S_SEQ]
            if state == WRITING or i in pinned:
                continue
            if state != PUBLISHED:
                return i
            tag = q[b + S_TAG]
            if seq == newest[tag]:
                continue
            if unread and (seq > unread.get(None, seq) or q[b + S_TAG_SEQ] > unread.get(tag, q[b + S_TAG_SEQ])):
                continue  # unread by a FIFO reader and the policy forbids overwriting it
            key = (-held.get(tag, 0), seq)
            if best_key is None or key < best_key:
                best, best_key = i, key
        return best

    def acquire(self, timeout: float | None = None, should_stop: Callable[[], bool] | None = None) -> SlotInfo | None:
        """A slot to fill, or None: full under ``drop_newest`` (counted), or ``block`` timed out / stopped."""
        ring, q = self.ring, self.ring._q

        def take() -> SlotInfo | None:
            i = self._choose()
            if i is not None:
                b = ring._slot(i)
                q[b + S_STATE] = WRITING
                q[b + S_SEQ] = 0
                q[b + S_PID] = ring._pid
                q[H_WRITER_WAITING] = 0
                return SlotInfo(i, ring.views[i])
            if ring._policy == OVERFLOW_CODE["drop_newest"]:
                q[H_DROPPED_NEWEST] += 1
            elif ring._policy == OVERFLOW_CODE["drop_oldest"]:  # pragma: no cover - excluded by create()
                raise RuntimeError(f"ring {ring.name!r}: no free slot; n_slots must be >= readers + 2")
            else:
                q[H_WRITER_WAITING] = 1
            return None

        # drop_newest never waits: one look, and a full ring drops the new item (counted above)
        drop_newest = ring._policy == OVERFLOW_CODE["drop_newest"]
        return ring._wait(RELEASE_WORD_OFF, take, 0.0 if drop_newest else timeout, should_stop)

    def publish(
        self,
        slot: SlotInfo,
        frame_id: int,
        t_capture: float,
        t_submit: float,
        origin: int | None = None,
        tag: int = 0,
    ) -> int:
        """Make a filled slot visible to readers and wake them. The slot's content must be complete, or its device
        work queued before an event its readers wait on (Note [Event hand-off] in runtime/handoff.py).

        ``origin`` carries the frame's identity down the pipeline; None means this ring is the input ring and
        the new slot's own seq is the origin. ``tag``: the frame's camera (Note [Tagged slots]).
        """
        return self._publish(slot, frame_id, t_capture, t_submit, origin, None, tag)[0]

    def publish_pinned(
        self, slot: SlotInfo, frame_id: int, t_capture: float, t_submit: float, reader: RingReader, tag: int = 0
    ) -> SlotInfo:
        """``publish`` an input-ring slot already pinned for ``reader`` (which must pin nothing), the read counted,
        in the same critical section, before any other reader can see it: how a reader whose work on the slot was
        queued before it was published keeps it (Note [Inline launch] in runtime/handoff.py). Returns the pin."""
        pinned = self._publish(slot, frame_id, t_capture, t_submit, None, reader, tag)[1]
        assert pinned is not None
        return pinned

    def _publish(
        self,
        slot: SlotInfo,
        frame_id: int,
        t_capture: float,
        t_submit: float,
        origin: int | None,
        pin_for: RingReader | None,
        tag: int = 0,
    ) -> tuple[int, SlotInfo | None]:
        ring, q, d = self.ring, self.ring._q, self.ring._d
        b = ring._slot(slot.index)
        now = time.monotonic()
        pinned = None
        if not 0 <= tag < ring.n_tags:
            raise ValueError(f"ring {ring.name!r} has {ring.n_tags} tags; got tag {tag}")
        with ring._mutex:
            if pin_for is not None:
                pin_for._check_unpinned()
            seq = q[H_LAST_SEQ] + 1
            tag_seq = q[ring._t0 + tag] + 1
            q[b + S_TAG] = tag
            q[b + S_TAG_SEQ] = tag_seq
            q[b + S_SEQ] = seq
            q[b + S_FRAME] = frame_id
            q[b + S_ORIGIN] = seq if origin is None else origin
            d[b + S_TCAP] = t_capture
            d[b + S_TSUB] = t_submit
            d[b + S_TPUB] = now
            q[b + S_STATE] = PUBLISHED  # last: a reader never sees a published slot with stale metadata
            q[H_LAST_SEQ] = seq
            q[ring._t0 + tag] = tag_seq
            q[H_PUBLISHED] += 1
            ring._bump(PUBLISH_WORD_OFF)
            if pin_for is not None:
                pinned = pin_for._pin_locked(slot.index)
        ring._wake(PUBLISH_WORD_OFF)
        slot.seq, slot.frame_id, slot.t_capture, slot.t_submit, slot.t_publish = (
            seq,
            frame_id,
            t_capture,
            t_submit,
            now,
        )
        slot.origin = seq if origin is None else origin
        slot.tag, slot.tag_seq = tag, tag_seq
        return seq, pinned

    def abort(self, slot: SlotInfo) -> None:
        """Give back a slot that will not be published (the work that should fill it failed)."""
        ring, q = self.ring, self.ring._q
        b = ring._slot(slot.index)
        with ring._mutex:
            q[b + S_STATE] = EMPTY
            q[b + S_SEQ] = 0
