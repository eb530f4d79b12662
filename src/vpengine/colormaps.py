"""Colour tables for depth pictures: 256x3 uint8 BGR, the same on the GPU (``models/dpt.py``) and on the host
(``visualize.py``).

The common matplotlib maps ship with the package (``colormaps.npz``, made from matplotlib's own tables), so drawing
depth needs no matplotlib; any other matplotlib name works where matplotlib is installed.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

_SHIPPED = Path(__file__).with_name("colormaps.npz")


@lru_cache(maxsize=1)
def shipped() -> dict[str, np.ndarray]:
    """The tables that ship with the package, by matplotlib name."""
    with np.load(_SHIPPED) as z:
        tables = {name: z[name] for name in z.files}
    for table in tables.values():
        table.flags.writeable = False  # shared by every caller
    return tables


@lru_cache(maxsize=16)
def lut(name: str = "Spectral_r") -> np.ndarray:
    """256x3 uint8 BGR table of the matplotlib colormap ``name`` (Depth-Anything-V2 draws with Spectral_r).

    Raises ValueError naming the accepted maps when ``name`` is neither shipped nor a matplotlib map."""
    tables = shipped()
    if name in tables:
        return tables[name]
    accepted = ", ".join(tables)
    try:
        import matplotlib
    except ModuleNotFoundError:
        raise ValueError(
            f"unknown colormap {name!r}; accepted: {accepted} (pip install matplotlib for any matplotlib colormap)"
        ) from None
    try:
        cmap = matplotlib.colormaps[name]
    except KeyError:
        raise ValueError(f"unknown colormap {name!r}; accepted: {accepted} or any matplotlib colormap") from None
    rgb = (cmap(np.linspace(0, 1, 256))[:, :3] * 255).round().astype(np.uint8)
    table = np.ascontiguousarray(rgb[:, ::-1])
    table.flags.writeable = False
    return table
