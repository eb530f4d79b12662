"""Slot rings: the mailboxes between models. One writer, N named readers, K preallocated slots.

Two flavours share this code and differ only in how a reader picks a slot and how the writer overflows:

* :class:`LatestBuffer` (circular, newest wins): a reader pins the newest slot newer than what it last saw; every
  frame it never saw is counted as *missed* (skipped). The writer overwrites the oldest slot nobody pins.
* :class:`FifoQueue` (bounded, ordered): a reader pins the next slot in sequence order; a slot overwritten before
  the reader got to it is counted as *missed* (dropped). On overflow the writer applies a policy: ``drop_oldest``
  (overwrite the oldest unread; in a ring of several cameras, the oldest of the camera that holds the most: Note
  [Tagged slots]), ``drop_newest`` (refuse the new item, counted), or ``block`` (wait for a reader).

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
each tag for readers that have not looked yet, so a ring needs readers + tags + 1 slots (with one tag: readers + 2),
and tags - 1 more where the writer fills a slot per tag before it publishes them (a batch of every camera's frames).
Where it must overwrite, it takes the oldest slot of the camera that holds the most slots no reader pins (a lent
result is not its camera's to give up), not the oldest of all: a camera whose frames come faster, or whose reader
keeps up, then gives up its own older slots rather than another camera's, so each camera keeps its share of the
ring (an output ring's ``output.slots`` a camera, which a caller waiting for a slower camera's outputs relies on).

The ring is this module's ``SlotRing`` (creation, attachment, supervision, stats, the one futex wait), its
``RingReader`` (ring_reader.py) and ``RingWriter`` (ring_writer.py), over the metadata offsets and descriptions of
ring_meta.py; import them all from here.

Crash safety: each critical section writes its fields in an order where any prefix is harmless. If a process dies
holding the mutex, the next locker gets EOWNERDEAD and carries on; the supervisor then calls
:meth:`SlotRing.release_reader` / :meth:`SlotRing.reset_writer` for the dead process.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import replace
from typing import TypeVar

import torch

from vpengine.specs import SpecDict
from vpengine.transport import linux
from vpengine.transport.layout import SlotLayout
from vpengine.transport.memory import HostRegion, allocate, open_region
from vpengine.transport.region import Region, RegionHandle
from vpengine.transport.ring_meta import (
    EMPTY,
    H_DROPPED_NEWEST,
    H_LAST_SEQ,
    H_N_READERS,
    H_N_SLOTS,
    H_PUBLISHED,
    H_WRITER_WAITING,
    MODE_CODE,
    OVERFLOW_CODE,
    PUBLISH_WORD_OFF,
    PUBLISHED,
    R_ACTIVE,
    R_CURSOR,
    R_MISSED,
    R_MODE,
    R_PINNED,
    R_READS,
    RELEASE_WORD_OFF,
    RF,
    S_FRAME,
    S_ORIGIN,
    S_SEQ,
    S_STATE,
    S_TAG,
    S_TAG_SEQ,
    S_TCAP,
    S_TPUB,
    S_TSUB,
    SF,
    SLOTS,
    WRITING,
    Accept,
    Overflow,
    ReaderDecl,
    ReaderMode,
    RingDesc,
    SlotInfo,
    meta_bytes,
)
from vpengine.transport.ring_reader import RingReader
from vpengine.transport.ring_writer import RingWriter

__all__ = [
    "Accept",
    "Overflow",
    "ReaderDecl",
    "ReaderMode",
    "RingDesc",
    "RingReader",
    "RingWriter",
    "SlotInfo",
    "SlotRing",
    "fifo_queue",
    "latest_buffer",
]

T = TypeVar("T")

#: Longest single futex sleep. Waits are re-checked at least this often so stop flags are seen promptly even if a
#: wake-up is missed for any reason (they are not, but a robot should not depend on that).
_MAX_SLEEP = 0.25


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
        self._addr = meta.address()  # a futex word's address: this plus its offset
        self._reader_index = {r.name: i for i, r in enumerate(desc.readers)}
        self._r0 = SLOTS + self.n_slots * SF
        self.n_tags = desc.n_tags
        self._t0 = self._r0 + len(desc.readers) * RF  # the tag table
        self._policy = OVERFLOW_CODE[desc.overflow]
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
        if overflow not in OVERFLOW_CODE:
            raise ValueError(f"ring {name!r}: unknown overflow policy {overflow!r}; accepted: {list(OVERFLOW_CODE)}")
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
        meta = HostRegion(f"{name}.meta", meta_bytes(n_slots, len(readers), n_tags))
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
        q[H_N_SLOTS] = n_slots
        q[H_N_READERS] = len(readers)
        r0 = SLOTS + n_slots * SF
        for i, r in enumerate(readers):
            base = r0 + i * RF
            q[base + R_ACTIVE] = 1 if r.active else 0
            q[base + R_MODE] = MODE_CODE[r.mode]
            q[base + R_PINNED] = -1
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
        return self._q[self._slot(i) + S_TAG]

    # ------------------------------------------------------------------------------------------- internals
    def _slot(self, i: int) -> int:
        return SLOTS + i * SF

    def _reader(self, r: int) -> int:
        return self._r0 + r * RF

    def _slot_info(self, i: int, tensors: bool = True) -> SlotInfo:
        b = self._slot(i)
        q, d = self._q, self._d
        return SlotInfo(
            i,
            self.views[i] if tensors else {},
            q[b + S_SEQ],
            q[b + S_FRAME],
            d[b + S_TCAP],
            d[b + S_TSUB],
            d[b + S_TPUB],
            q[b + S_ORIGIN],
            tag=q[b + S_TAG],
            tag_seq=q[b + S_TAG_SEQ],
        )

    def _bump(self, word: int) -> None:
        """Move futex word ``word`` (PUBLISH_WORD_OFF, RELEASE_WORD_OFF) on, so that a sleeper that read it before
        does not sleep; the caller holds the mutex and calls ``_wake(word)`` after letting go of it."""
        self._u[word // 4] = (self._u[word // 4] + 1) & 0xFFFFFFFF

    def _wake(self, word: int) -> None:
        linux.futex_wake(self._addr + word)

    def _wait(
        self,
        word: int,
        poll: Callable[[], T | None],
        timeout: float | None,
        should_stop: Callable[[], bool] | None,
    ) -> T | None:
        """The one futex wait of a ring: sleep on ``word`` until ``poll()``, called under the mutex, returns
        something (returned), or ``should_stop()`` says so, or ``timeout`` seconds pass (None: no limit); None
        then. The word is read in the same critical section as ``poll`` looked, so a publish or release that
        comes after the look has moved it and the sleep returns at once: no wake-up is lost."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            with self._mutex:
                found = poll()
                if found is not None:
                    return found
                seen = self._u[word // 4]
            if should_stop is not None and should_stop():
                return None
            remaining = _MAX_SLEEP if deadline is None else deadline - time.monotonic()
            if remaining <= 0:
                return None
            linux.futex_wait(self._addr + word, seen, min(remaining, _MAX_SLEEP))

    def wake_all(self) -> None:
        """Wake every sleeper on this ring (used at stop so waits end at once)."""
        with self._mutex:
            self._bump(PUBLISH_WORD_OFF)
            self._bump(RELEASE_WORD_OFF)
        self._wake(PUBLISH_WORD_OFF)
        self._wake(RELEASE_WORD_OFF)

    def wait_any(
        self, readers: list[RingReader], timeout: float, should_stop: Callable[[], bool] | None = None
    ) -> bool:
        """Sleep until one of ``readers`` (readers of this ring, e.g. one per camera: Note [Tagged slots]) has a slot
        to pin, or ``timeout`` passes; pins nothing. Whether one has."""

        def ready() -> bool | None:
            return True if any(r._find(False) is not None for r in readers) else None

        return self._wait(PUBLISH_WORD_OFF, ready, timeout, should_stop) is not None

    def notify_readers(self) -> None:
        """Wake readers waiting to pin, without a publish: what they may take has changed (a pin filter that
        accepts more now, see ``RingReader.pin``)."""
        with self._mutex:
            self._bump(PUBLISH_WORD_OFF)
        self._wake(PUBLISH_WORD_OFF)

    def _unpin(self, index: int, expect: int | None = None) -> int | None:
        """Drop reader ``index``'s pin and wake a writer blocked for a free slot. ``expect``: the slot it must pin
        (RuntimeError otherwise). Returns the origin of the slot it held (None: none)."""
        q, r = self._q, self._reader(index)
        with self._mutex:
            pinned = q[r + R_PINNED]
            if expect is not None and pinned != expect:
                name = self.desc.readers[index].name
                raise RuntimeError(f"reader {name!r} does not pin slot {expect} of ring {self.name!r}")
            held = None if pinned < 0 else int(q[self._slot(int(pinned)) + S_ORIGIN])
            q[r + R_PINNED] = -1
            waiting = q[H_WRITER_WAITING]
            if waiting:
                self._bump(RELEASE_WORD_OFF)
        if waiting:
            self._wake(RELEASE_WORD_OFF)
        return held

    # -------------------------------------------------------------------------------------- supervision
    def release_reader(self, name: str) -> int | None:
        """Drop the pin of a reader whose process died. Returns the origin of the slot it held (None: none)."""
        return self._unpin(self._reader_index[name])

    def rename_reader(self, old: str, new: str) -> None:
        """Give reader ``old`` the name ``new`` in this process (a seat taken or given back, Note [Heads at run
        time] in runtime/lanes.py); a process that attaches after it sees the new name. Other processes address
        readers by index."""
        if new in self._reader_index:
            raise ValueError(f"ring {self.name!r} has a reader {new!r} already")
        index = self._reader_index[old]
        readers = list(self.desc.readers)
        readers[index] = replace(readers[index], name=new)
        self.desc = replace(self.desc, readers=tuple(readers))
        # a new dict, not this one changed: other threads iterate it meanwhile (stats)
        self._reader_index = {r.name: i for i, r in enumerate(readers)}

    def clear_reader(self, name: str) -> None:
        """Make reader ``name`` inactive and forget what it read, missed and pins: a seat given back."""
        index = self._reader_index[name]
        self._unpin(index)
        q, r = self._q, self._reader(index)
        with self._mutex:
            for field in (R_ACTIVE, R_CURSOR, R_READS, R_MISSED):
                q[r + field] = 0

    def reset_writer(self) -> int:
        """Forget slots a dead writer left half-written. Returns how many there were."""
        q = self._q
        n = 0
        with self._mutex:
            last = 0
            for i in range(self.n_slots):
                b = self._slot(i)
                if q[b + S_STATE] == WRITING:
                    q[b + S_STATE] = EMPTY
                    q[b + S_SEQ] = 0
                    n += 1
                elif q[b + S_STATE] == PUBLISHED:
                    last = max(last, q[b + S_SEQ])
            q[H_LAST_SEQ] = max(q[H_LAST_SEQ], last)
            q[H_WRITER_WAITING] = 0
        return n

    def pins(self) -> dict[str, int]:
        """Which slot each reader pins (-1: none)."""
        with self._mutex:
            return {n: self._q[self._reader(i) + R_PINNED] for n, i in self._reader_index.items()}

    def stats(self) -> dict[str, object]:
        """Counters: published, dropped_newest, and per reader reads / missed / pending."""
        q = self._q
        with self._mutex:
            last = q[H_LAST_SEQ]
            readers = {}
            for n, i in self._reader_index.items():
                b = self._reader(i)
                active = bool(q[b + R_ACTIVE])
                tag = self.desc.readers[i].tag
                newest = last if tag is None else q[self._t0 + tag]  # in the reader's own sequence
                readers[n] = {
                    "active": active,
                    "reads": q[b + R_READS],
                    "missed": q[b + R_MISSED],
                    "pending": (newest - q[b + R_CURSOR]) if active else 0,
                    "pinned": q[b + R_PINNED] >= 0,
                }
            return {
                "published": q[H_PUBLISHED],
                "last_seq": last,
                "dropped_newest": q[H_DROPPED_NEWEST],
                "readers": readers,
            }

    @property
    def last_seq(self) -> int:
        return self._q[H_LAST_SEQ]


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
