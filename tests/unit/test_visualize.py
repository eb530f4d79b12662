"""Pictures of outputs (``vpengine.visualize``), against plain NumPy written the obvious way."""

from __future__ import annotations

import numpy as np
import pytest

from vpengine.colormaps import lut as colormap_lut
from vpengine.visualize import (
    caption,
    colorize_depth,
    default_palette,
    depth_picture,
    detections,
    draw_detections,
    draw_result,
    draw_results,
    overlay_segmentation,
)

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
        np.testing.assert_array_equal(out.reshape(-1, 3)[np.nanargmin(np.where(np.isfinite(d), d, np.nan))], lut[0])
        np.testing.assert_array_equal(out.reshape(-1, 3)[np.nanargmax(np.where(np.isfinite(d), d, np.nan))], lut[255])


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


def test_class_colours_are_far_apart():
    pal = default_palette(16).astype(np.float64)[1:]  # 0 is the grey of background
    dist = np.sqrt(((pal[:, None] - pal[None]) ** 2).sum(-1))
    assert dist[~np.eye(len(pal), dtype=bool)].min() >= 60
    assert (default_palette(1000)[0] == 60).all() and len({tuple(c) for c in default_palette(256)}) == 256


def test_a_caption_is_text_on_a_filled_box_inside_the_picture_in_a_colour_that_reads():
    img = np.full((100, 200, 3), 128, np.uint8)
    x1, y1, x2, y2 = caption(img, "depth", (190, 95), (255, 255, 255), 0.5)  # asked to start off the picture
    assert 0 <= x1 < x2 == 200 and 0 <= y1 < y2 == 100  # moved inside
    box = img[y1:y2, x1:x2].reshape(-1, 3)
    assert (box == 255).all(-1).mean() > 0.6 and (box < 100).all(-1).any()  # white box, dark text on it
    assert (img[:y1] == 128).all() and (img[:, :x1] == 128).all()  # nothing outside the box
    dark = np.zeros((50, 100, 3), np.uint8)
    x1, y1, x2, y2 = caption(dark, "seg", (0, 0), (90, 0, 0))
    assert (dark[y1:y2, x1:x2] > 200).all(-1).any()  # white text on a dark box


def test_depth_pictures_have_a_colour_bar_labelled_with_the_range():
    d = np.tile(np.linspace(2.0, 9.0, 320, dtype=np.float32), (240, 1))
    pic = depth_picture(d)
    plain = colorize_depth(d)
    assert pic.shape == plain.shape and (pic != plain).any()
    bw = 320 // 40
    x = 320 - bw - 4 + bw // 2  # the middle of the bar
    bar = pic[:, x]
    lut = colormap_lut()
    rows = np.flatnonzero((bar[:, None, :] == lut[None, [0, 255], :]).all(-1).any(-1))
    top, bottom = rows.min(), rows.max()
    np.testing.assert_array_equal(bar[top], lut[255])  # the largest value at the top
    np.testing.assert_array_equal(bar[bottom], lut[0])
    assert bottom - top >= 0.5 * 240
    np.testing.assert_array_equal(pic[:, :150], plain[:, :150])  # the map itself is untouched
    assert (depth_picture(d, bar=False) == plain).all()


def test_detections_are_the_first_count_of_a_fixed_capacity_output_each_class_in_its_colour():
    out = {
        "boxes": np.array([[10, 40, 60, 90], [100, 40, 150, 90], [0, 0, 0, 0]], np.float32),
        "scores": np.array([0.9, 0.8, 0.0], np.float32),
        "labels": np.array([1, 2, -1], np.int32),
        "count": np.array(2, np.int32),
    }
    boxes, scores, labels = detections(out)
    assert boxes.shape == (2, 4) and labels.tolist() == [1, 2]
    pic = draw_detections(np.zeros((120, 160, 3), np.uint8), boxes, scores, labels, ["a", "b", "c"])
    left, right = tuple(pic[65, 10]), tuple(pic[65, 100])  # on each box's left edge
    assert left != right and left != (0, 0, 0) and right != (0, 0, 0)
    assert not pic[100:, :].any()  # the padded third box is not drawn


def test_one_heads_result_is_drawn_in_the_frames_grid_whatever_its_size():
    frame = RNG.integers(0, 256, (120, 160, 3)).astype(np.uint8)
    depth = draw_result(frame, {"depth": RNG.random((60, 80)).astype(np.float32)}, {"kind": "depth"}, "depth")
    seg = draw_result(frame, {"classes": np.zeros((30, 40), np.uint8)}, {"kind": "segmentation"})
    det = draw_result(
        frame, {"boxes": np.zeros((0, 4)), "scores": np.zeros(0), "labels": np.zeros(0, int)}, None, "det"
    )
    assert depth.shape == seg.shape == det.shape == frame.shape
    # class 0 everywhere: the frame blended with class 0's colour, except under the legend at the top left
    want = overlay_segmentation(frame, np.zeros((120, 160), np.uint8))
    np.testing.assert_array_equal(seg[60:], want[60:])
    np.testing.assert_array_equal(det[60:], frame[60:])  # no boxes: the frame below its title


@pytest.mark.parametrize(
    ("size", "heads", "grid", "tile"),
    [
        ((120, 160), 3, (2, 2), (360, 480)),  # a small frame is shown larger, so its captions stay readable
        ((576, 768), 2, (1, 3), (480, 640)),  # three pictures in a row within 1920 pixels
        ((1080, 1920), 3, (2, 2), (540, 960)),
        ((1080, 1920), 4, (2, 3), (360, 640)),
    ],
)
def test_all_heads_side_by_side(size, heads, grid, tile):
    frame = RNG.integers(0, 256, (*size, 3)).astype(np.uint8)
    results = {
        "depth": {"depth": RNG.random(size).astype(np.float32)},
        "seg": {"classes": RNG.integers(0, 5, size).astype(np.uint8)},
        "det": {"boxes": np.array([[10, 10, 50, 50]]), "scores": np.array([0.5]), "labels": np.array([0])},
        "other": None,
    }
    results = dict(list(results.items())[:heads])
    mosaic = draw_results(frame, results)
    assert mosaic.shape == (grid[0] * tile[0], grid[1] * tile[1], 3)
    import cv2

    first = cv2.resize(frame, tile[::-1], interpolation=cv2.INTER_AREA if tile[0] < size[0] else cv2.INTER_LINEAR)
    np.testing.assert_array_equal(mosaic[tile[0] // 2 : tile[0], : tile[1]], first[tile[0] // 2 :])  # the input
    if "other" in results:  # never answered yet: the frame, darkened, with a caption
        r, c = divmod(heads, grid[1])
        cell = mosaic[r * tile[0] : (r + 1) * tile[0], c * tile[1] : (c + 1) * tile[1]]
        np.testing.assert_array_equal(cell[tile[0] // 2 :], first[tile[0] // 2 :] // 3)


@pytest.mark.parametrize("hw", [(1, 1), (1, 300), (300, 1), (2, 3)])
def test_every_kind_of_picture_of_a_frame_of_odd_shape_has_the_frames_shape(hw):
    """A 1xN frame's maps are 1xN, never squeezed to a vector (or a 1x1's to a scalar), and drawn at its size."""
    from vpengine.visualize import plane

    frame = RNG.integers(0, 256, (*hw, 3), dtype=np.uint8)
    depth = RNG.random(hw).astype(np.float32)
    classes = RNG.integers(0, 5, hw).astype(np.uint8)
    for shape in (hw, (*hw, 1), (1, *hw)):  # a map, and the two singleton axes a head may add
        assert plane(depth.reshape(shape), hw).shape == hw
    boxes = np.array([[0, 0, hw[1], hw[0]]], np.float32)
    outputs = [
        {"depth": depth},
        {"depth": depth[..., None]},
        {"depth": depth[None]},
        {"classes": classes},
        {"boxes": boxes, "scores": np.ones(1, np.float32), "labels": np.zeros(1, np.int32)},
    ]
    for out in outputs:
        assert draw_result(frame, out, title="head").shape == (*hw, 3)
        assert draw_results(frame, {"head": out}).ndim == 3


def test_a_box_of_zero_width_or_height_is_not_drawn_and_has_no_caption():
    """Note [Empty boxes]: a caption with no box names nothing, so neither is drawn."""
    image = np.full((60, 80, 3), 128, np.uint8)
    empty = np.array([[80, 10, 80, 40], [5, 60, 50, 60], [10, 10, 10, 10], [np.nan, 0, 5, 5]], np.float32)
    out = draw_detections(image, empty, np.full(4, 0.9, np.float32), np.arange(4), ["a", "b", "c", "d"])
    np.testing.assert_array_equal(out, image)
    one = draw_detections(image, np.array([[10, 10, 30, 40]], np.float32), np.ones(1), np.zeros(1, np.int32))
    assert (one != image).any()  # a real box still is


def test_a_declared_kind_without_its_outputs_is_generic_not_another_kind():
    """Note [Kinds and outputs]: a detection head whose labels are named classes is no segmentation head (its 1-D
    classes drawn or written as a map crashed); a head with no kind is taken by its output names."""
    from vpengine.visualize import head_kind

    assert head_kind({"kind": "detection", "outputs": {"boxes": 0, "scores": 0, "classes": 0}}) == "generic"
    assert head_kind({"kind": "segmentation", "outputs": {"mask": 0}}) == "generic"
    assert head_kind({"kind": "depth", "outputs": {"depth_color": 0}}) == "depth"  # its picture alone: still depth
    assert head_kind({"kind": "detection"}) == "detection"  # no outputs known to check
    assert head_kind({"outputs": {"classes": 0}}) == "segmentation"  # no kind: by its names
