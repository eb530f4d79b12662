"""What every memory backend is (``memory.py``: host and local regions; ``cuda_vmm.py``: device memory shared
between processes): one contiguous allocation viewable as a flat uint8 tensor, and the picklable handle another
process maps it with."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class RegionHandle:
    """Picklable description of an exported region; the fd it needs travels separately at ``fd_index``."""

    kind: str
    name: str
    nbytes: int
    fd_index: int
    device: int = -1
    #: Backend-specific extras (the CUDA backend records its allocation granularity here).
    alloc_bytes: int = 0


class Region(ABC):
    """One allocation, viewable as a flat uint8 tensor on ``device``."""

    kind: str = ""

    def __init__(self, name: str, nbytes: int, device: torch.device) -> None:
        self.name = name
        self.nbytes = nbytes
        self.device = device

    @abstractmethod
    def tensor(self) -> torch.Tensor:
        """The whole region as a flat uint8 tensor (zero-copy)."""

    def export(self, fds: list[int]) -> RegionHandle:
        raise TypeError(f"region {self.name!r} ({self.kind}) cannot be shared with another process")

    @abstractmethod
    def close(self) -> None:
        """Unmap and free this process's references. Safe to call twice."""

    def keep_mapped(self) -> object:
        """An object that keeps this process's mapping of the region valid for as long as it lives, even past
        ``close()``: what arrays handed to a caller hold (Note [Borrowed results] in engine/results.py)."""
        raise TypeError(f"region {self.name!r} ({self.kind}) cannot outlive close()")
