"""Slot layout: one allocation per pool, carved into per-slot, per-key views.

::

    region (one allocation)
    +--------------------------- slot 0 ---------------------------+---- slot 1 ----+ ...
    | key a (aligned to 256 B) | key b (aligned) | ... | pad to 256 |  same offsets  |
    +--------------------------------------------------------------+----------------+

Tiny tensors (a CLS token, a detection count) share the slot with the large ones instead of each getting an
allocation of its own (the reference implementation paid 2 MiB of device memory per tiny tensor).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from vpengine.specs import SpecDict, TensorSpec

#: Alignment of every tensor inside a slot: enough for vectorised loads on any device.
ALIGN = 256


def _round_up(n: int, a: int) -> int:
    return (n + a - 1) // a * a


@dataclass(frozen=True)
class SlotLayout:
    keys: tuple[str, ...]
    specs: tuple[TensorSpec, ...]
    offsets: tuple[int, ...]
    slot_bytes: int
    n_slots: int

    @classmethod
    def from_specs(cls, specs: SpecDict, n_slots: int) -> SlotLayout:
        if n_slots < 1:
            raise ValueError(f"n_slots must be at least 1, got {n_slots}")
        offsets = []
        off = 0
        for spec in specs.values():
            offsets.append(off)
            off = _round_up(off + spec.nbytes, ALIGN)
        return cls(tuple(specs), tuple(specs.values()), tuple(offsets), max(off, ALIGN), n_slots)

    @property
    def total_bytes(self) -> int:
        return self.slot_bytes * self.n_slots

    def views(self, flat: torch.Tensor) -> list[dict[str, torch.Tensor]]:
        """Per-slot dicts of tensors viewing ``flat`` (a uint8 tensor of at least ``total_bytes``)."""
        if flat.dtype != torch.uint8 or flat.numel() < self.total_bytes:
            raise ValueError(f"need a uint8 buffer of {self.total_bytes} bytes, got {flat.dtype}[{flat.numel()}]")
        out = []
        for s in range(self.n_slots):
            base = s * self.slot_bytes
            views = {}
            for key, spec, off in zip(self.keys, self.specs, self.offsets):
                raw = flat[base + off : base + off + spec.nbytes]
                views[key] = raw.view(spec.torch_dtype).view(spec.shape)
            out.append(views)
        return out
