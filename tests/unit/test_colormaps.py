"""Colour tables ship with the package and equal matplotlib's; other names need matplotlib and say so."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from vpengine import colormaps


def test_shipped_tables_are_matplotlibs():
    matplotlib = pytest.importorskip("matplotlib")
    tables = colormaps.shipped()
    assert {"Spectral_r", "turbo", "inferno", "viridis"} <= set(tables)
    for name, table in tables.items():
        rgb = (matplotlib.colormaps[name](np.linspace(0, 1, 256))[:, :3] * 255).round().astype(np.uint8)
        assert table.shape == (256, 3) and table.dtype == np.uint8
        np.testing.assert_array_equal(table, rgb[:, ::-1], err_msg=name)  # BGR
        assert not table.flags.writeable  # shared by every caller


def test_depth_colours_need_no_matplotlib(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises
    colormaps.lut.cache_clear()
    try:
        assert colormaps.lut("Spectral_r").shape == (256, 3)
        with pytest.raises(
            ValueError, match=r"unknown colormap 'cividis'; accepted: Spectral_r.*pip install matplotlib"
        ):
            colormaps.lut("cividis")
    finally:
        colormaps.lut.cache_clear()


def test_other_matplotlib_names_and_unknown_names():
    pytest.importorskip("matplotlib")
    assert colormaps.lut("cividis").shape == (256, 3)
    with pytest.raises(ValueError, match=r"unknown colormap 'nope'; accepted: .* or any matplotlib colormap"):
        colormaps.lut("nope")
