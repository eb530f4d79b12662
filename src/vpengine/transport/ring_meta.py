"""What a ring's writer, readers and owner share: the offsets of its metadata region (Note [Ring memory layout] in
ring.py), the descriptions another process attaches by, and the slot a reader pins or a writer fills.

Nothing here touches the region itself; ``SlotRing`` (ring.py) owns it, ``RingReader`` (ring_reader.py) and
``RingWriter`` (ring_writer.py) work on it under the ring's lock.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch

from vpengine.transport.layout import SlotLayout
from vpengine.transport.region import RegionHandle

Overflow = Literal["drop_oldest", "drop_newest", "block"]
#: A reader's pin filter: (slot index, seq) -> whether it may take that slot now.
Accept = Callable[[int, int], bool]
ReaderMode = Literal["latest", "fifo"]

EMPTY, WRITING, PUBLISHED = 0, 1, 2
MODE_CODE = {"latest": 1, "fifo": 2}
OVERFLOW_CODE = {"drop_oldest": 0, "drop_newest": 1, "block": 2}

# Byte offsets of the two futex words; every other index below counts i64 words of the metadata region.
PUBLISH_WORD_OFF, RELEASE_WORD_OFF = 64, 68
_H = 9  # header starts at byte 72
H_LAST_SEQ, H_N_SLOTS, H_N_READERS, H_WRITER_WAITING, H_PUBLISHED, H_DROPPED_NEWEST = range(_H, _H + 6)
SLOTS = 16  # slot table starts at byte 128
SF = 10  # fields per slot
S_STATE, S_SEQ, S_FRAME, S_TCAP, S_TSUB, S_TPUB, S_PID, S_ORIGIN, S_TAG, S_TAG_SEQ = range(10)
RF = 8  # fields per reader
R_ACTIVE, R_MODE, R_CURSOR, R_READS, R_MISSED, R_PINNED, R_PID = range(7)


def meta_bytes(n_slots: int, n_readers: int, n_tags: int) -> int:
    return SLOTS * 8 + n_slots * SF * 8 + n_readers * RF * 8 + n_tags * 8


@dataclass(frozen=True)
class ReaderDecl:
    name: str
    mode: ReaderMode = "latest"
    #: Active readers count what they miss from the first publish on; inactive ones start counting at activate().
    active: bool = True
    #: Only slots published with this tag (a camera's index), Note [Tagged slots] in ring.py; None: every slot.
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
    #: The tag it was published with (a camera's index, Note [Tagged slots] in ring.py) and its place in that tag's
    #: sequence.
    tag: int = 0
    tag_seq: int = 0
