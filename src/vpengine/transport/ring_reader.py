"""A named reader of a slot ring: what it pins next, pins by origin or by another reader's slot, and releases.

The rules it keeps are Note [Slot lifetime] and Note [Tagged slots] in ring.py; the ring's lock guards every read
of the metadata here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from vpengine.transport.ring_meta import (
    H_LAST_SEQ,
    MODE_CODE,
    PUBLISH_WORD_OFF,
    PUBLISHED,
    R_ACTIVE,
    R_CURSOR,
    R_MISSED,
    R_MODE,
    R_PID,
    R_PINNED,
    R_READS,
    S_ORIGIN,
    S_SEQ,
    S_STATE,
    S_TAG,
    S_TAG_SEQ,
    Accept,
    SlotInfo,
)

if TYPE_CHECKING:
    from vpengine.transport.ring import SlotRing


class RingReader:
    """One named reader of a ring. Holds at most one pin at a time."""

    def __init__(self, ring: SlotRing, index: int) -> None:
        self.ring = ring
        self.index = index
        self.name = ring.desc.readers[index].name
        #: The tag this reader sees (Note [Tagged slots]); None: every slot. Its cursor counts in that tag's sequence.
        self.tag = ring.desc.readers[index].tag
        self._b = ring._reader(index)
        self._mode = ring._q[self._b + R_MODE]

    # ------------------------------------------------------------------------------------------ activation
    def activate(self, from_now: bool = True) -> None:
        """Start counting: ``from_now`` skips everything published so far (it is neither read nor missed)."""
        ring, q = self.ring, self.ring._q
        with ring._mutex:
            if not q[self._b + R_ACTIVE]:
                if from_now:
                    q[self._b + R_CURSOR] = q[H_LAST_SEQ] if self.tag is None else q[ring._t0 + self.tag]
                q[self._b + R_ACTIVE] = 1

    @property
    def active(self) -> bool:
        return bool(self.ring._q[self._b + R_ACTIVE])

    @property
    def cursor(self) -> int:
        """Sequence number of the last slot this reader read (0: none); a tagged reader's, in its tag's sequence."""
        return self.ring._q[self._b + R_CURSOR]

    # -------------------------------------------------------------------------------------------- reading
    def _find(self, peek: bool, accept: Accept | None = None) -> int | None:
        """The slot to pin next; ``accept(index, seq)``: only a slot it accepts. A peek then takes the newest such
        slot; a read takes its usual slot only once accepted (never one out of order)."""
        ring, q = self.ring, self.ring._q
        cursor = q[self._b + R_CURSOR]
        fifo = self._mode == MODE_CODE["fifo"] and not peek
        tag = self.tag
        best, best_seq = None, None
        for i in range(ring.n_slots):
            b = ring._slot(i)
            if q[b + S_STATE] != PUBLISHED or (tag is not None and q[b + S_TAG] != tag):
                continue
            seq = q[b + S_SEQ]
            if not peek and (seq if tag is None else q[b + S_TAG_SEQ]) <= cursor:
                continue
            if peek and accept is not None and not accept(i, seq):
                continue
            if best_seq is None or (seq < best_seq if fifo else seq > best_seq):
                best, best_seq = i, seq
        if accept is not None and not peek and best is not None and best_seq is not None and not accept(best, best_seq):
            return None
        return best

    def _check_unpinned(self) -> None:
        """RuntimeError if this reader pins a slot (it holds one at a time); the caller holds the ring's mutex."""
        pinned = self.ring._q[self._b + R_PINNED]
        if pinned >= 0:
            raise RuntimeError(
                f"reader {self.name!r} of ring {self.ring.name!r} already pins a slot ({pinned}); "
                "release it before pinning another"
            )

    def pin_origin(self, origin: int, tag: int | None = None) -> tuple[SlotInfo | None, int]:
        """Pin (peek, no accounting) the published slot derived from input ``origin``, if still there.

        Returns ``(slot or None, newest origin published so far)``; a newest origin past ``origin`` with no slot
        means the frame was skipped or already overwritten. ``tag``: the newest among that camera's slots only
        (Note [Tagged slots]): the cameras' frames are published each in its own order, not in one, so another
        camera's newer frame says nothing about this one.
        """
        ring, q = self.ring, self.ring._q
        b = self._b
        with ring._mutex:
            self._check_unpinned()
            newest = 0
            found = None
            for i in range(ring.n_slots):
                sb = ring._slot(i)
                if q[sb + S_STATE] != PUBLISHED:
                    continue
                o = q[sb + S_ORIGIN]
                if tag is None or q[sb + S_TAG] == tag:
                    newest = max(newest, o)
                if o == origin:
                    found = i
            if found is None:
                return None, newest
            q[b + R_PINNED] = found
            return ring._slot_info(found), newest

    def pin_slot(self, slot: SlotInfo) -> SlotInfo | None:
        """Pin the slot that ``slot`` (pinned by another reader) describes, without accounting; None if it no longer
        holds that output (not published, or a different sequence number).

        While the other reader still pins it the slot cannot change, so this reader takes it over and keeps it
        after the other releases: how ``Engine`` lends a result without copying it (Note [Borrowed results]).
        """
        ring, q = self.ring, self.ring._q
        b = self._b
        with ring._mutex:
            self._check_unpinned()
            sb = ring._slot(slot.index)
            if q[sb + S_STATE] != PUBLISHED or q[sb + S_SEQ] != slot.seq:
                return None
            q[b + R_PINNED] = slot.index
            q[b + R_PID] = ring._pid
            return ring._slot_info(slot.index)

    def available(self) -> bool:
        with self.ring._mutex:
            return self._find(False) is not None

    def pin(
        self,
        timeout: float = 0.0,
        should_stop: Callable[[], bool] | None = None,
        peek: bool = False,
        accept: Accept | None = None,
    ) -> SlotInfo | None:
        """Pin the next slot for this reader (newest unseen, or next in order for FIFO readers).

        Waits up to ``timeout`` seconds for one (0: do not wait); returns None on timeout or when ``should_stop``
        says so. ``peek`` pins the newest published slot even if already seen, without counting anything.
        ``accept(index, seq)``: only a slot it accepts (e.g. one whose device work is done, when its writer
        publishes queued work; whoever makes it accept more calls ``SlotRing.notify_readers``). The returned
        tensors are views into the pool: use them, then :meth:`release`.
        """

        def take() -> SlotInfo | None:
            self._check_unpinned()
            i = self._find(peek, accept)
            return None if i is None else self._pin_locked(i, peek)

        return self.ring._wait(PUBLISH_WORD_OFF, take, timeout, should_stop)

    def _pin_locked(self, i: int, peek: bool = False) -> SlotInfo:
        """Pin published slot ``i`` and count the read (not a peek); the caller holds the ring's mutex."""
        ring, q, b = self.ring, self.ring._q, self._b
        q[b + R_PINNED] = i
        q[b + R_PID] = ring._pid
        info = ring._slot_info(i)
        if not peek:
            cursor = q[b + R_CURSOR]
            mine = info.seq if self.tag is None else info.tag_seq  # Note [Tagged slots]
            if q[b + R_ACTIVE]:
                info.missed = mine - cursor - 1
                q[b + R_MISSED] += info.missed
                q[b + R_READS] += 1
            q[b + R_CURSOR] = mine
        return info

    def release(self, slot: SlotInfo | None = None) -> None:
        """Unpin. The work that read the slot's tensors must be complete (see Note [Slot lifetime])."""
        self.ring._unpin(self.index, None if slot is None else slot.index)

    def wait(self, timeout: float, should_stop: Callable[[], bool] | None = None) -> bool:
        """Sleep until something is there to pin (without pinning it) or the timeout passes."""
        return self.ring.wait_any([self], timeout, should_stop)
