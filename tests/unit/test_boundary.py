"""The boundary's geometry (Note [Frame grid] in boundary.py): fitting a frame into the input canvas and mapping
outputs back into the frame's pixel grid, for numpy arrays and tensors alike."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from tests_paths import tiny
from vpengine.boundary import SIZES_KEPT, Boundary, Placement, buffer_for, output_kinds
from vpengine.specs import TensorSpec


def test_a_frame_of_the_canvas_size_is_the_identity():
    p = Placement.fit((120, 160), (120, 160))
    assert p.identity and (p.x0, p.y0, p.w, p.h) == (0, 0, 160, 120)


@pytest.mark.parametrize(
    ("frame", "region"),
    [
        ((240, 320), (0, 0, 160, 120)),  # same aspect: scaled, no bands
        ((1080, 1920), (0, 15, 160, 90)),  # wider: bands top and bottom
        ((480, 480), (20, 0, 120, 120)),  # narrower: bands left and right
        ((60, 80), (0, 0, 160, 120)),  # smaller: scaled up
    ],
)
def test_a_frame_keeps_its_aspect_and_is_centred(frame, region):
    p = Placement.fit(frame, (120, 160))
    assert (p.x0, p.y0, p.w, p.h) == region
    assert abs(p.w / frame[1] - p.h / frame[0]) < 0.02  # never stretched


def test_boxes_come_back_in_frame_pixels_clipped_to_the_frame():
    p = Placement.fit((1080, 1920), (120, 160))  # region x 0..160, y 15..105, scale 1/12
    canvas = np.array([[0, 15, 160, 105], [80, 60, 90, 70], [-5, 0, 10, 200]], np.float32)
    got = p.boxes_to_frame(canvas)
    np.testing.assert_allclose(got[0], [0, 0, 1920, 1080])
    np.testing.assert_allclose(got[1], [960, 540, 1080, 660])
    np.testing.assert_allclose(got[2], [0, 0, 120, 1080])  # clipped to the frame
    assert got.dtype == np.float32
    torch.testing.assert_close(p.boxes_to_frame(torch.from_numpy(canvas)), torch.from_numpy(got))


def test_maps_are_cut_out_of_the_bands_and_resized_to_the_frame():
    p = Placement.fit((1080, 1920), (120, 160))
    depth = np.full((120, 160), -1.0, np.float32)  # the bands hold garbage
    depth[15:105] = np.linspace(0, 1, 160, dtype=np.float32)[None, :]
    out = p.map_to_frame(depth, labels=False)
    assert out.shape == (1080, 1920) and out.dtype == np.float32
    assert out.min() >= 0 and out.max() <= 1  # nothing of the bands leaks in
    assert np.all(np.diff(out[540]) >= -1e-6)  # the gradient survives
    colour = np.zeros((120, 160, 3), np.uint8)
    colour[15:105] = (10, 20, 30)
    assert (p.map_to_frame(colour, labels=False) == (10, 20, 30)).all()


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.int32, np.int64])
def test_class_maps_take_the_nearest_class_and_keep_their_dtype(dtype):
    p = Placement.fit((240, 480), (120, 160))  # scaled by 1/3: region y 20..100
    classes = np.zeros((120, 160), dtype)
    classes[20:100, :80] = 3
    classes[20:100, 80:] = 7
    out = p.map_to_frame(classes, labels=True)
    assert out.shape == (240, 480) and out.dtype == dtype
    assert set(np.unique(out)) == {3, 7}  # no mixed or band classes
    assert (out[:, :240] == 3).all() and (out[:, 240:] == 7).all()
    t = p.map_to_frame(torch.from_numpy(classes), labels=True)
    assert t.dtype == torch.from_numpy(classes).dtype and torch.equal(t, torch.from_numpy(out))


def test_output_kinds_are_declared_or_inferred_from_the_canvas_shape():
    spec = {
        "depth": TensorSpec((120, 160), "float32"),
        "ids": TensorSpec((120, 160), "int32"),
        "boxes": TensorSpec((8, 4), "float32"),
        "scores": TensorSpec((8,), "float32"),
        "mask": TensorSpec((60, 80), "uint8"),
    }
    assert output_kinds({}, spec, (120, 160)) == {"depth": "map", "ids": "labels", "boxes": "boxes"}
    assert output_kinds({"output_grid": {"mask": "labels"}}, spec, (120, 160))["mask"] == "labels"
    with pytest.raises(ValueError, match="one of"):
        output_kinds({"output_grid": {"mask": "blob"}}, spec, (120, 160))


def test_a_wide_frame_is_written_scaled_with_its_aspect_between_bands_of_the_mean_colour():
    b = Boundary(tiny("thread"), {})
    wide = np.random.default_rng(0).integers(0, 256, (120, 320, 3), np.uint8)
    dst = np.zeros((120, 160, 3), np.uint8)
    p = b.write(wide, dst)
    assert (p.x0, p.y0, p.w, p.h) == (0, 30, 160, 60)
    np.testing.assert_array_equal(dst[30:90], cv2.resize(wide, (160, 60), interpolation=cv2.INTER_AREA))
    mean_bgr = np.round(np.array([0.406, 0.456, 0.485]) * 255)  # ImageNet's, the backbones': zero once normalised
    assert (dst[:30] == mean_bgr).all() and (dst[90:] == mean_bgr).all()
    same = np.random.default_rng(1).integers(0, 256, (120, 160, 3), np.uint8)
    assert b.write(same, dst).identity and (dst == same).all()


def test_frames_of_ever_new_sizes_keep_a_bounded_number_of_buffers():
    b = Boundary(tiny("thread"), {})
    dst = np.zeros((120, 160, 3), np.uint8)
    rng = np.random.default_rng(2)
    for w in range(200, 200 + 4 * SIZES_KEPT, 4):  # a folder of images, each of another size
        b.write(rng.integers(0, 256, (100, w, 3), np.uint8), dst)
        assert len(b._scratch) <= SIZES_KEPT
    cache: dict = {}
    first = buffer_for(cache, (10, 20), np.uint8)
    for i in range(SIZES_KEPT - 1):
        buffer_for(cache, (11 + i, 20), np.uint8)
    assert buffer_for(cache, (10, 20), np.uint8) is first  # used again: kept, now the most recent
    buffer_for(cache, (99, 99), np.uint8)  # one size too many: the least recently used goes, not the first
    assert (10, 20) in cache and (11, 20) not in cache and len(cache) == SIZES_KEPT
