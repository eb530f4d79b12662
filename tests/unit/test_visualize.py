"""Pictures of outputs (``vpengine.io.visualize``), against plain NumPy written the obvious way."""

from __future__ import annotations

import numpy as np
import pytest

from vpengine.io.visualize import colorize_depth, colormap_lut, default_palette, overlay_segmentation

RNG = np.random.default_rng(7)


def reference_colorize(d: np.ndarray, lo: float | None = None, hi: float | None = None) -> np.ndarray:
    finite = np.isfinite(d)
    lo = float(d[finite].min()) if lo is None else lo
    hi = float(d[finite].max()) if hi is None else hi
    scaled = np.where(finite, (d - np.float32(lo)) / np.float32(max(hi - lo, 1e-12)), 0).astype(np.float32)
    idx = np.round(np.clip(scaled, 0, 1) * np.float32(255)).astype(np.uint8)
    out = colormap_lut()[idx]
    out[~finite] = 0
    return out


@pytest.mark.parametrize("shape", [(1080, 1920), (37, 53), (1, 1), (9,)])
@pytest.mark.parametrize("holes", ["none", "nan", "inf"])
def test_depth_colours_are_the_scaled_map_looked_up_and_non_finite_pixels_are_black(shape, holes):
    d = (RNG.random(shape) * 40 + 0.5).astype(np.float32)
    if holes == "nan":
        d.flat[1::7] = np.nan
    elif holes == "inf":
        d.flat[1::5], d.flat[2::5] = np.inf, -np.inf
    out = colorize_depth(d)
    assert out.shape == (*shape, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out, reference_colorize(d))
    np.testing.assert_array_equal(colorize_depth(d, lo=10, hi=20), reference_colorize(d, 10, 20))
    if holes != "none":
        assert not out[~np.isfinite(d)].any()
    if d.size > 2:  # the nearest and the farthest finite pixels get the colour map's two ends
        lut = colormap_lut()
        np.testing.assert_array_equal(
            out.reshape(-1, 3)[np.nanargmin(np.where(np.isfinite(d), d, np.nan))], lut[0]
        )
        np.testing.assert_array_equal(
            out.reshape(-1, 3)[np.nanargmax(np.where(np.isfinite(d), d, np.nan))], lut[255]
        )


def test_a_flat_or_empty_depth_map_gives_one_colour_or_black():
    np.testing.assert_array_equal(
        colorize_depth(np.full((4, 5), 3.0, np.float32)), np.broadcast_to(colormap_lut()[0], (4, 5, 3))
    )
    assert not colorize_depth(np.full((4, 5), np.nan, np.float32)).any()


@pytest.mark.parametrize(
    ("dtype", "n", "palette"),
    [
        (np.uint8, 150, None),
        (np.uint8, 150, 150),  # a palette shorter than 256
        (np.uint8, 200, 300),  # and longer
        (np.uint16, 300, None),
        (np.int64, 12, None),
    ],
)
def test_the_overlay_is_the_rounded_blend_of_frame_and_class_colours(dtype, n, palette):
    img = RNG.integers(0, 256, (120, 160, 3)).astype(np.uint8)
    classes = RNG.integers(0, n, (120, 160)).astype(dtype)
    pal = None if palette is None else default_palette(palette, seed=11)
    used = default_palette(max(n, 256)) if pal is None else pal
    colour = used[classes.astype(np.int64)].astype(np.float64)
    for alpha in (0.0, 0.3, 0.5, 1.0):
        out = overlay_segmentation(img, classes, pal, alpha=alpha)
        want = img * (1 - alpha) + colour * alpha
        assert out.dtype == np.uint8 and out.shape == img.shape
        assert np.abs(out - want).max() <= 0.5 + 1e-6, alpha
    np.testing.assert_array_equal(overlay_segmentation(img, classes, pal, alpha=1.0), colour.astype(np.uint8))
    np.testing.assert_array_equal(overlay_segmentation(img, classes, pal, alpha=0.0), img)


def test_the_overlay_resizes_the_frame_to_the_class_map_and_refuses_a_frame_that_is_not_bgr_uint8():
    img = RNG.integers(0, 256, (240, 320, 3)).astype(np.uint8)
    classes = np.zeros((120, 160), np.uint8)
    assert overlay_segmentation(img, classes).shape == (120, 160, 3)
    with pytest.raises(ValueError, match=r"uint8 \(H, W, 3\) image, got float32"):
        overlay_segmentation(img.astype(np.float32), classes)
    with pytest.raises(ValueError, match=r"got uint8 \(240, 320\)"):
        overlay_segmentation(img[..., 0], classes)
