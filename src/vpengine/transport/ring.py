"""Slot rings: the mailboxes between models. One writer, N named readers, K preallocated slots.

Two flavours share this code and differ only in how a reader picks a slot and how the writer overflows:

* :class:`LatestBuffer` (circular, newest wins): a reader pins the newest slot newer than what it last saw; every
  frame it never saw is counted as *missed* (skipped). The writer overwrites the oldest slot nobody pins.
* :class:`FifoQueue` (bounded, ordered): a reader pins the next slot in sequence order; a slot overwritten before
  the reader got to it is counted as *missed* (dropped). On overflow the writer applies a policy: ``drop_oldest``
  (overwrite the oldest unread), ``drop_newest`` (refuse the new item, counted), or ``block`` (wait for a reader).

Every reader can also *peek* (pin the newest slot whether seen or not, no accounting), which ``Engine.latest`` uses.

Note [Ring memory layout]
~~~~~~~~~~~~~~~~~~~~~~~~~
The tensors live in one data region (see ``layout.py``): host shared memory, a local tensor, or CUDA VMM memory.
The metadata lives in a small host region shared by every process that uses the ring::

    [0, 64)     robust process-shared pthread mutex guarding everything below
    [64, 68)    u32 futex word ``publish_word``: bumped on every publish, readers sleep on it
    [68, 72)    u32 futex word ``release_word``: bumped when a blocked writer must look again
    [72, 128)   header, i64 x 7: last_seq, n_slots, n_readers, writer_waiting, published, dropped_newest, reserved
    [128, ...)  slot table, n_slots x 10 i64: state, seq, frame_id, t_capture*, t_submit*, t_publish*, writer_pid,
                origin (the input-ring seq of the frame this slot derives from: frame identity across the pipeline),
                tag, tag_seq (Note [Tagged slots])
    [...]       reader table, n_readers x 8 i64: active, mode, cursor, reads, missed, pinned_slot, pid, -
    [...]       tag table, n_tags x i64: the last tag_seq published with each tag
                (* stored as float64 in the same 8 bytes)

Note [Slot lifetime]
~~~~~~~~~~~~~~~~~~~~
A slot is EMPTY, WRITING or PUBLISHED. The writer only takes a slot that no reader pins, is not the newest
published one, and (for ``drop_newest``/``block``) that every FIFO reader has already read; it marks the slot
WRITING, fills the tensors *outside* the lock, and publishes it (seq, frame id, times) only once the work that
filled it is complete (the device-sync rule lives in the runtime: a CUDA writer synchronises its stream first).
A reader only pins PUBLISHED slots, uses the tensors in place, and releases after the work that read them is
complete. Hence a pinned slot is never written and a published slot is always whole: no torn reads, no copies.
With ``n_slots >= n_readers + 2`` the writer always finds a slot (each reader pins at most one, plus the newest),
so ``LatestBuffer`` writers never wait; ``create`` enforces this.

Note [Tagged slots]
~~~~~~~~~~~~~~~~~~~
Frames of several cameras share one ring (one writer, one order of publication, frame identity by origin as ever),
each slot published with its camera's index as its *tag*. A reader declared with a tag sees only that tag's slots,
as if the ring held that camera's frames alone: its cursor, the frames it missed and what is pending count in the
tag's own sequence (``tag_seq``), so a model that reads every camera holds one such reader per camera and pins at
most one slot per camera. A reader without a tag sees every slot, as before. The writer keeps the newest slot of
each tag for readers that have not looked yet, so a ring needs readers + tags + 1 slots (with one tag: readers + 2).

Crash safety: each critical section writes its fields in an order where any prefix is harmless. If a process dies
holding the mutex, the next locker gets EOWNERDEAD and carries on; the supervisor then calls
:meth:`SlotRing.release_reader` / :meth:`SlotRing.reset_writer` for the dead process.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch

from vpengine.specs import SpecDict
from vpengine.transport import linux
from vpengine.transport.layout import SlotLayout
from vpengine.transport.memory import HostRegion, allocate, open_region
from vpengine.transport.region import Region, RegionHandle

Overflow = Literal["drop_oldest", "drop_newest", "block"]
#: A reader's pin filter: (slot index, seq) -> whether it may take that slot now.
Accept = Callable[[int, int], bool]
ReaderMode = Literal["latest", "fifo"]

_EMPTY, _WRITING, _PUBLISHED = 0, 1, 2
_MODE_CODE = {"latest": 1, "fifo": 2}
_OVERFLOW_CODE = {"drop_oldest": 0, "drop_newest": 1, "block": 2}

# i64 indices into the metadata region
_PUBLISH_WORD_OFF, _RELEASE_WORD_OFF = 64, 68
_H = 9  # header starts at byte 72
_H_LAST_SEQ, _H_N_SLOTS, _H_N_READERS, _H_WRITER_WAITING, _H_PUBLISHED, _H_DROPPED_NEWEST = range(_H, _H + 6)
_SLOTS = 16  # slot table starts at byte 128
_SF = 10  # fields per slot
_S_STATE, _S_SEQ, _S_FRAME, _S_TCAP, _S_TSUB, _S_TPUB, _S_PID, _S_ORIGIN, _S_TAG, _S_TAG_SEQ = range(10)
_RF = 8  # fields per reader
_R_ACTIVE, _R_MODE, _R_CURSOR, _R_READS, _R_MISSED, _R_PINNED, _R_PID = range(7)

#: Longest single futex sleep. Waits are re-checked at least this often so stop flags are seen promptly even if a
#: wake-up is missed for any reason (they are not, but a robot should not depend on that).
_MAX_SLEEP = 0.25


@dataclass(frozen=True)
class ReaderDecl:
    name: str
    mode: ReaderMode = "latest"
    #: Active readers count what they miss from the first publish on; inactive ones start counting at activate().
    active: bool = True
    #: Only slots published with this tag (a camera's index), Note [Tagged slots]; None: every slot.
    tag: int | None = None


@dataclass(frozen=True)
class RingDesc:
    """Everything another process needs to attach to a ring (picklable; fds travel separately)."""

    name: str
    layout: SlotLayout
    readers: tuple[ReaderDecl, ...]
    overflow: Overflow
    meta: RegionHandle
    data: RegionHandle
    n_tags: int = 1


@dataclass
class SlotInfo:
    """A pinned or writable slot: its index, its metadata and its tensors (views into the pool)."""

    index: int
    tensors: dict[str, torch.Tensor]
    seq: int = 0
    frame_id: int = -1
    t_capture: float = 0.0
    t_submit: float = 0.0
    t_publish: float = 0.0
    #: The input-ring sequence number of the frame this slot derives from (set by the first writer).
    origin: int = 0
    #: Frames published between the previous read of this reader and this one that it never saw.
    missed: int = 0
    #: The tag it was published with (a camera's index, Note [Tagged slots]) and its place in that tag's sequence.
    tag: int = 0
    tag_seq: int = 0


def _meta_bytes(n_slots: int, n_readers: int, n_tags: int) -> int:
    return _SLOTS * 8 + n_slots * _SF * 8 + n_readers * _RF * 8 + n_tags * 8


class SlotRing:
    """A preallocated ring of slots with one writer and named readers. See the module docstring."""

    def __init__(self, desc: RingDesc, meta: HostRegion, data: Region, *, owner: bool) -> None:
        self.desc = desc
        self.name = desc.name
        self.layout = desc.layout
        self.n_slots = desc.layout.n_slots
        self._meta = meta
        self._data = data
        self._owner = owner
        mv = memoryview(meta.mm)
        self._q = mv.cast("q")
        self._d = mv.cast("d")
        self._u = mv.cast("I")
        self._mutex = linux.RobustMutex(meta.address())
        self._publish_addr = meta.address() + _PUBLISH_WORD_OFF
        self._release_addr = meta.address() + _RELEASE_WORD_OFF
        self._reader_index = {r.name: i for i, r in enumerate(desc.readers)}
        self._r0 = _SLOTS + self.n_slots * _SF
        self.n_tags = desc.n_tags
        self._t0 = self._r0 + len(desc.readers) * _RF  # the tag table
        self._policy = _OVERFLOW_CODE[desc.overflow]
        self.views = desc.layout.views(data.tensor())
        self._pid = os.getpid()

    # ----------------------------------------------------------------------------------------------- creation
    @classmethod
    def create(
        cls,
        name: str,
        specs: SpecDict,
        n_slots: int,
        readers: list[ReaderDecl],
        device: torch.device | str = "cpu",
        shared: bool = True,
        overflow: Overflow = "drop_oldest",
        pinned: bool = False,
        n_tags: int = 1,
    ) -> SlotRing:
        """Allocate a ring: one data region for all slots and one metadata region.

        ``pinned``: the data is host memory that a GPU copies to or from (see ``allocate``).
        """
        if overflow not in _OVERFLOW_CODE:
            raise ValueError(f"ring {name!r}: unknown overflow policy {overflow!r}; accepted: {list(_OVERFLOW_CODE)}")
        names = [r.name for r in readers]
        if len(set(names)) != len(names):
            raise ValueError(f"ring {name!r}: reader names must be unique, got {names}")
        bad_tags = [r.name for r in readers if r.tag is not None and not 0 <= r.tag < n_tags]
        if n_tags < 1 or bad_tags:
            raise ValueError(f"ring {name!r}: {n_tags} tags; readers with a tag out of range: {bad_tags}")
        if n_slots < len(readers) + n_tags + 1:
            raise ValueError(
                f"ring {name!r}: n_slots={n_slots} is too small for {len(readers)} readers and {n_tags} tags; need at "
                f"least {len(readers) + n_tags + 1} (readers + tags + 1) so the writer never waits and pinned slots "
                "are never overwritten"
            )
        layout = SlotLayout.from_specs(specs, n_slots)
        meta = HostRegion(f"{name}.meta", _meta_bytes(n_slots, len(readers), n_tags))
        try:
            data = allocate(f"{name}.data", layout.total_bytes, device, shared, pinned)
        except (OSError, RuntimeError) as e:  # ENOMEM from mmap, a CUDA out-of-memory error
            meta.close()
            raise MemoryError(
                f"ring {name!r}: cannot allocate {layout.total_bytes / 1e9:.2f} GB ({n_slots} slots of "
                f"{layout.slot_bytes} bytes) on {device}: {e}"
            ) from e
        except BaseException:
            meta.close()
            raise
        linux.mutex_init(meta.address())
        q = memoryview(meta.mm).cast("q")
        q[_H_N_SLOTS] = n_slots
        q[_H_N_READERS] = len(readers)
        r0 = _SLOTS + n_slots * _SF
        for i, r in enumerate(readers):
            base = r0 + i * _RF
            q[base + _R_ACTIVE] = 1 if r.active else 0
            q[base + _R_MODE] = _MODE_CODE[r.mode]
            q[base + _R_PINNED] = -1
        q.release()
        handles: list[int] = []
        desc = RingDesc(
            name,
            layout,
            tuple(readers),
            overflow,
            meta.export(handles) if shared else RegionHandle("host", meta.name, meta.nbytes, -1),
            data.export(handles) if shared else RegionHandle(data.kind, data.name, data.nbytes, -1),
            n_tags,
        )
        return cls(desc, meta, data, owner=True)

    def export(self, fds: list[int]) -> RingDesc:
        """Description for another process; appends the two fds it needs to ``fds``."""
        meta = self._meta.export(fds)
        data = self._data.export(fds)
        d = self.desc
        return RingDesc(d.name, d.layout, d.readers, d.overflow, meta, data, d.n_tags)

    @classmethod
    def attach(cls, desc: RingDesc, fds: list[int]) -> SlotRing:
        meta = open_region(desc.meta, fds)
        assert isinstance(meta, HostRegion)
        return cls(desc, meta, open_region(desc.data, fds), owner=False)

    @property
    def data_region(self) -> Region:
        return self._data

    def close(self) -> None:
        self.views = []
        for mv in (self._q, self._d, self._u):
            mv.release()
        self._meta.close()
        self._data.close()

    # --------------------------------------------------------------------------------------------- handles
    def writer(self) -> RingWriter:
        return RingWriter(self)

    def reader(self, name: str) -> RingReader:
        if name not in self._reader_index:
            raise KeyError(f"ring {self.name!r} has no reader {name!r}; readers: {list(self._reader_index)}")
        return RingReader(self, self._reader_index[name])

    def slot_tag(self, i: int) -> int:
        """The tag slot ``i`` was last published with (Note [Tagged slots]); for a pin filter (``Accept``), which
        runs under the ring's lock."""
        return self._q[self._slot(i) + _S_TAG]

    # ------------------------------------------------------------------------------------------- internals
    def _slot(self, i: int) -> int:
        return _SLOTS + i * _SF

    def _reader(self, r: int) -> int:
        return self._r0 + r * _RF

    def _slot_info(self, i: int, tensors: bool = True) -> SlotInfo:
        b = self._slot(i)
        q, d = self._q, self._d
        return SlotInfo(
            i,
            self.views[i] if tensors else {},
            q[b + _S_SEQ],
            q[b + _S_FRAME],
            d[b + _S_TCAP],
            d[b + _S_TSUB],
            d[b + _S_TPUB],
            q[b + _S_ORIGIN],
            tag=q[b + _S_TAG],
            tag_seq=q[b + _S_TAG_SEQ],
        )

    def _wake_publish(self) -> None:
        linux.futex_wake(self._publish_addr)

    def wake_all(self) -> None:
        """Wake every sleeper on this ring (used at stop so waits end at once)."""
        with self._mutex:
            self._u[_PUBLISH_WORD_OFF // 4] = (self._u[_PUBLISH_WORD_OFF // 4] + 1) & 0xFFFFFFFF
            self._u[_RELEASE_WORD_OFF // 4] = (self._u[_RELEASE_WORD_OFF // 4] + 1) & 0xFFFFFFFF
        linux.futex_wake(self._publish_addr)
        linux.futex_wake(self._release_addr)

    def wait_any(
        self, readers: list[RingReader], timeout: float, should_stop: Callable[[], bool] | None = None
    ) -> bool:
        """Sleep until one of ``readers`` (readers of this ring, e.g. one per camera: Note [Tagged slots]) has a slot
        to pin, or ``timeout`` passes; pins nothing. Whether one has."""
        deadline = time.monotonic() + timeout
        while True:
            with self._mutex:
                if any(r._find(False) is not None for r in readers):
                    return True
                word = self._u[_PUBLISH_WORD_OFF // 4]
            if should_stop is not None and should_stop():
                return False
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            linux.futex_wait(self._publish_addr, word, min(remaining, _MAX_SLEEP))

    def notify_readers(self) -> None:
        """Wake readers waiting to pin, without a publish: what they may take has changed (a pin filter that
        accepts more now, see ``RingReader.pin``)."""
        with self._mutex:
            self._u[_PUBLISH_WORD_OFF // 4] = (self._u[_PUBLISH_WORD_OFF // 4] + 1) & 0xFFFFFFFF
        self._wake_publish()

    # -------------------------------------------------------------------------------------- supervision
    def release_reader(self, name: str) -> int | None:
        """Drop the pin of a reader whose process died. Returns the origin of the slot it held (None: none)."""
        r = self._reader(self._reader_index[name])
        with self._mutex:
            pinned = self._q[r + _R_PINNED]
            held = None if pinned < 0 else int(self._q[self._slot(int(pinned)) + _S_ORIGIN])
            self._q[r + _R_PINNED] = -1
            waiting = self._q[_H_WRITER_WAITING]
            if waiting:
                self._u[_RELEASE_WORD_OFF // 4] = (self._u[_RELEASE_WORD_OFF // 4] + 1) & 0xFFFFFFFF
        if waiting:
            linux.futex_wake(self._release_addr)
        return held

    def reset_writer(self) -> int:
        """Forget slots a dead writer left half-written. Returns how many there were."""
        q = self._q
        n = 0
        with self._mutex:
            last = 0
            for i in range(self.n_slots):
                b = self._slot(i)
                if q[b + _S_STATE] == _WRITING:
                    q[b + _S_STATE] = _EMPTY
                    q[b + _S_SEQ] = 0
                    n += 1
                elif q[b + _S_STATE] == _PUBLISHED:
                    last = max(last, q[b + _S_SEQ])
            q[_H_LAST_SEQ] = max(q[_H_LAST_SEQ], last)
            q[_H_WRITER_WAITING] = 0
        return n

    def pins(self) -> dict[str, int]:
        """Which slot each reader pins (-1: none)."""
        with self._mutex:
            return {n: self._q[self._reader(i) + _R_PINNED] for n, i in self._reader_index.items()}

    def stats(self) -> dict[str, object]:
        """Counters: published, dropped_newest, and per reader reads / missed / pending."""
        q = self._q
        with self._mutex:
            last = q[_H_LAST_SEQ]
            readers = {}
            for n, i in self._reader_index.items():
                b = self._reader(i)
                active = bool(q[b + _R_ACTIVE])
                tag = self.desc.readers[i].tag
                newest = last if tag is None else q[self._t0 + tag]  # in the reader's own sequence
                readers[n] = {
                    "active": active,
                    "reads": q[b + _R_READS],
                    "missed": q[b + _R_MISSED],
                    "pending": (newest - q[b + _R_CURSOR]) if active else 0,
                    "pinned": q[b + _R_PINNED] >= 0,
                }
            return {
                "published": q[_H_PUBLISHED],
                "last_seq": last,
                "dropped_newest": q[_H_DROPPED_NEWEST],
                "readers": readers,
            }

    @property
    def last_seq(self) -> int:
        return self._q[_H_LAST_SEQ]


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
            if q[b + _R_PINNED] >= 0:
                pinned.add(q[b + _R_PINNED])
            if ring._policy != 0 and q[b + _R_ACTIVE] and q[b + _R_MODE] == _MODE_CODE["fifo"]:
                c = q[b + _R_CURSOR]
                unread[decl.tag] = min(unread.get(decl.tag, c), c)
        newest: dict[int, int] = {}  # tag -> its newest published seq, kept for readers that have not looked yet
        for i in range(ring.n_slots):
            b = ring._slot(i)
            if q[b + _S_STATE] == _PUBLISHED:
                t = q[b + _S_TAG]
                newest[t] = max(newest.get(t, 0), q[b + _S_SEQ])
        best, best_seq = None, None
        for i in range(ring.n_slots):
            b = ring._slot(i)
            state, seq = q[b + _S_STATE], q[b + _S_SEQ]
            if state == _WRITING or i in pinned:
                continue
            if state == _PUBLISHED:
                tag = q[b + _S_TAG]
                if seq == newest[tag]:
                    continue
                if unread and (seq > unread.get(None, seq) or q[b + _S_TAG_SEQ] > unread.get(tag, q[b + _S_TAG_SEQ])):
                    continue  # unread by a FIFO reader and the policy forbids overwriting it
            if best_seq is None or seq < best_seq:
                best, best_seq = i, seq
        return best

    def acquire(self, timeout: float | None = None, should_stop: Callable[[], bool] | None = None) -> SlotInfo | None:
        """A slot to fill, or None: full under ``drop_newest`` (counted), or ``block`` timed out / stopped."""
        ring, q, u = self.ring, self.ring._q, self.ring._u
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            with ring._mutex:
                i = self._choose()
                if i is not None:
                    b = ring._slot(i)
                    q[b + _S_STATE] = _WRITING
                    q[b + _S_SEQ] = 0
                    q[b + _S_PID] = ring._pid
                    q[_H_WRITER_WAITING] = 0
                    return SlotInfo(i, ring.views[i])
                if ring._policy == _OVERFLOW_CODE["drop_newest"]:
                    q[_H_DROPPED_NEWEST] += 1
                    return None
                if ring._policy == _OVERFLOW_CODE["drop_oldest"]:  # pragma: no cover - excluded by create()
                    raise RuntimeError(f"ring {ring.name!r}: no free slot; n_slots must be >= readers + 2")
                q[_H_WRITER_WAITING] = 1
                word = u[_RELEASE_WORD_OFF // 4]
            if should_stop is not None and should_stop():
                return None
            remaining = _MAX_SLEEP if deadline is None else deadline - time.monotonic()
            if remaining <= 0:
                return None
            linux.futex_wait(ring._release_addr, word, min(remaining, _MAX_SLEEP))

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
        ring, q, d, u = self.ring, self.ring._q, self.ring._d, self.ring._u
        b = ring._slot(slot.index)
        now = time.monotonic()
        pinned = None
        if not 0 <= tag < ring.n_tags:
            raise ValueError(f"ring {ring.name!r} has {ring.n_tags} tags; got tag {tag}")
        with ring._mutex:
            if pin_for is not None and q[pin_for._b + _R_PINNED] >= 0:
                raise RuntimeError(f"reader {pin_for.name!r} of ring {ring.name!r} already pins a slot")
            seq = q[_H_LAST_SEQ] + 1
            tag_seq = q[ring._t0 + tag] + 1
            q[b + _S_TAG] = tag
            q[b + _S_TAG_SEQ] = tag_seq
            q[b + _S_SEQ] = seq
            q[b + _S_FRAME] = frame_id
            q[b + _S_ORIGIN] = seq if origin is None else origin
            d[b + _S_TCAP] = t_capture
            d[b + _S_TSUB] = t_submit
            d[b + _S_TPUB] = now
            q[b + _S_STATE] = _PUBLISHED  # last: a reader never sees a published slot with stale metadata
            q[_H_LAST_SEQ] = seq
            q[ring._t0 + tag] = tag_seq
            q[_H_PUBLISHED] += 1
            u[_PUBLISH_WORD_OFF // 4] = (u[_PUBLISH_WORD_OFF // 4] + 1) & 0xFFFFFFFF
            if pin_for is not None:
                pinned = pin_for._pin_locked(slot.index)
        ring._wake_publish()
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
            q[b + _S_STATE] = _EMPTY
            q[b + _S_SEQ] = 0


class RingReader:
    """One named reader of a ring. Holds at most one pin at a time."""

    def __init__(self, ring: SlotRing, index: int) -> None:
        self.ring = ring
        self.index = index
        self.name = ring.desc.readers[index].name
        #: The tag this reader sees (Note [Tagged slots]); None: every slot. Its cursor counts in that tag's sequence.
        self.tag = ring.desc.readers[index].tag
        self._b = ring._reader(index)
        self._mode = ring._q[self._b + _R_MODE]

    # ------------------------------------------------------------------------------------------ activation
    def activate(self, from_now: bool = True) -> None:
        """Start counting: ``from_now`` skips everything published so far (it is neither read nor missed)."""
        ring, q = self.ring, self.ring._q
        with ring._mutex:
            if not q[self._b + _R_ACTIVE]:
                if from_now:
                    q[self._b + _R_CURSOR] = q[_H_LAST_SEQ] if self.tag is None else q[ring._t0 + self.tag]
                q[self._b + _R_ACTIVE] = 1

    @property
    def active(self) -> bool:
        return bool(self.ring._q[self._b + _R_ACTIVE])

    @property
    def cursor(self) -> int:
        """Sequence number of the last slot this reader read (0: none); a tagged reader's, in its tag's sequence."""
        return self.ring._q[self._b + _R_CURSOR]

    # -------------------------------------------------------------------------------------------- reading
    def _find(self, peek: bool, accept: Accept | None = None) -> int | None:
        """The slot to pin next; ``accept(index, seq)``: only a slot it accepts. A peek then takes the newest such
        slot; a read takes its usual slot only once accepted (never one out of order)."""
        ring, q = self.ring, self.ring._q
        cursor = q[self._b + _R_CURSOR]
        fifo = self._mode == _MODE_CODE["fifo"] and not peek
        tag = self.tag
        best, best_seq = None, None
        for i in range(ring.n_slots):
            b = ring._slot(i)
            if q[b + _S_STATE] != _PUBLISHED or (tag is not None and q[b + _S_TAG] != tag):
                continue
            seq = q[b + _S_SEQ]
            if not peek and (seq if tag is None else q[b + _S_TAG_SEQ]) <= cursor:
                continue
            if peek and accept is not None and not accept(i, seq):
                continue
            if best_seq is None or (seq < best_seq if fifo else seq > best_seq):
                best, best_seq = i, seq
        if accept is not None and not peek and best is not None and best_seq is not None and not accept(best, best_seq):
            return None
        return best

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
            if q[b + _R_PINNED] >= 0:
                raise RuntimeError(f"reader {self.name!r} of ring {ring.name!r} already pins a slot")
            newest = 0
            found = None
            for i in range(ring.n_slots):
                sb = ring._slot(i)
                if q[sb + _S_STATE] != _PUBLISHED:
                    continue
                o = q[sb + _S_ORIGIN]
                if tag is None or q[sb + _S_TAG] == tag:
                    newest = max(newest, o)
                if o == origin:
                    found = i
            if found is None:
                return None, newest
            q[b + _R_PINNED] = found
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
            if q[b + _R_PINNED] >= 0:
                raise RuntimeError(f"reader {self.name!r} of ring {ring.name!r} already pins a slot")
            sb = ring._slot(slot.index)
            if q[sb + _S_STATE] != _PUBLISHED or q[sb + _S_SEQ] != slot.seq:
                return None
            q[b + _R_PINNED] = slot.index
            q[b + _R_PID] = ring._pid
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
        publishes queued work; whoever makes it accept more calls ``SlotRing.notify_readers``). The returned tensors are views into the pool: use them, then
        :meth:`release`.
        """
        ring, q, u = self.ring, self.ring._q, self.ring._u
        b = self._b
        deadline = time.monotonic() + timeout
        while True:
            with ring._mutex:
                if q[b + _R_PINNED] >= 0:
                    raise RuntimeError(
                        f"reader {self.name!r} of ring {ring.name!r} already pins slot {q[b + _R_PINNED]}; "
                        "release it before pinning another"
                    )
                i = self._find(peek, accept)
                if i is not None:
                    return self._pin_locked(i, peek)
                word = u[_PUBLISH_WORD_OFF // 4]
            if should_stop is not None and should_stop():
                return None
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            linux.futex_wait(ring._publish_addr, word, min(remaining, _MAX_SLEEP))

    def _pin_locked(self, i: int, peek: bool = False) -> SlotInfo:
        """Pin published slot ``i`` and count the read (not a peek); the caller holds the ring's mutex."""
        ring, q, b = self.ring, self.ring._q, self._b
        q[b + _R_PINNED] = i
        q[b + _R_PID] = ring._pid
        info = ring._slot_info(i)
        if not peek:
            cursor = q[b + _R_CURSOR]
            mine = info.seq if self.tag is None else info.tag_seq  # Note [Tagged slots]
            if q[b + _R_ACTIVE]:
                info.missed = mine - cursor - 1
                q[b + _R_MISSED] += info.missed
                q[b + _R_READS] += 1
            q[b + _R_CURSOR] = mine
        return info

    def release(self, slot: SlotInfo | None = None) -> None:
        """Unpin. The work that read the slot's tensors must be complete (see Note [Slot lifetime])."""
        ring, q, u = self.ring, self.ring._q, self.ring._u
        with ring._mutex:
            if slot is not None and q[self._b + _R_PINNED] != slot.index:
                raise RuntimeError(f"reader {self.name!r} does not pin slot {slot.index} of ring {ring.name!r}")
            q[self._b + _R_PINNED] = -1
            waiting = q[_H_WRITER_WAITING]
            if waiting:
                u[_RELEASE_WORD_OFF // 4] = (u[_RELEASE_WORD_OFF // 4] + 1) & 0xFFFFFFFF
        if waiting:
            linux.futex_wake(ring._release_addr)

    def wait(self, timeout: float, should_stop: Callable[[], bool] | None = None) -> bool:
        """Sleep until something is there to pin (without pinning it) or the timeout passes."""
        ring, u = self.ring, self.ring._u
        deadline = time.monotonic() + timeout
        while True:
            with ring._mutex:
                if self._find(False) is not None:
                    return True
                word = u[_PUBLISH_WORD_OFF // 4]
            if should_stop is not None and should_stop():
                return False
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            linux.futex_wait(ring._publish_addr, word, min(remaining, _MAX_SLEEP))


def latest_buffer(name: str, specs: SpecDict, readers: list[str], n_slots: int | None = None, **kw: object) -> SlotRing:
    """A LatestBuffer: circular, newest wins; what a reader never saw is counted as missed (skipped)."""
    decls = [ReaderDecl(r, "latest") for r in readers]
    return SlotRing.create(name, specs, n_slots or len(readers) + 2, decls, **kw)  # type: ignore[arg-type]


def fifo_queue(
    name: str,
    specs: SpecDict,
    readers: list[str],
    n_slots: int,
    overflow: Overflow = "drop_oldest",
    **kw: object,
) -> SlotRing:
    """A FifoQueue: bounded and ordered; what the overflow policy dropped is counted (missed / dropped_newest)."""
    decls = [ReaderDecl(r, "fifo") for r in readers]
    return SlotRing.create(name, specs, n_slots, decls, overflow=overflow, **kw)  # type: ignore[arg-type]
