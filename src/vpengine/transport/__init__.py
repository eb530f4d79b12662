"""Preallocated slot pools and mailboxes. Knows tensors, slots, sequence numbers, pins and wake-ups; no models."""

from vpengine.transport.layout import SlotLayout
from vpengine.transport.memory import HostRegion, LocalRegion, allocate, open_region
from vpengine.transport.region import Region, RegionHandle
from vpengine.transport.ring import (
    ReaderDecl,
    RingDesc,
    RingReader,
    RingWriter,
    SlotInfo,
    SlotRing,
    fifo_queue,
    latest_buffer,
)

__all__ = [
    "HostRegion",
    "LocalRegion",
    "ReaderDecl",
    "Region",
    "RegionHandle",
    "RingDesc",
    "RingReader",
    "RingWriter",
    "SlotInfo",
    "SlotLayout",
    "SlotRing",
    "allocate",
    "fifo_queue",
    "latest_buffer",
    "open_region",
]
