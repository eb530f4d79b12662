"""The boundary's geometry (Note [Frame grid] in engine/boundary.py): fitting a frame into the input canvas and mapping
outputs back into the frame's pixel grid, for numpy arrays and tensors alike."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from tests_paths import tiny
from vpengine.engine.boundary import SIZES_KEPT, Boundary, Placement, buffer_for, output_kinds
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


@pytest.mark.parametrize(
    "dtype, labels, written", [(np.float32, False, True), (np.uint8, True, True), (np.int64, True, False)]
)
@pytest.mark.parametrize("frame_hw", [(300, 500), (40, 53)])  # scaled up (bilinear); shrunk by 3 (area-averaged)
def test_a_map_is_written_where_alloc_says_and_comes_out_the_same(dtype, labels, written, frame_hw):
    """The engine hands its recycled result arrays to ``map_to_frame`` (Note [Frame grid]): an OpenCV-resized 2-D map
    is written into the one given, with the values it has without; a map resized by hand is new memory as before."""
    p = Placement.fit(frame_hw, (120, 160))
    rng = np.random.default_rng(0)
    m = rng.integers(0, 150, (120, 160)).astype(dtype)
    given: list[np.ndarray] = []

    def alloc(shape, dt):
        given.append(np.full(shape, 99, dt))
        return given[-1]

    out = p.map_to_frame(m, labels=labels, alloc=alloc)
    np.testing.assert_array_equal(out, p.map_to_frame(m, labels=labels))
    assert out.shape == frame_hw and out.dtype == dtype
    assert (out is given[0]) if written else not given
    colour = rng.integers(0, 255, (120, 160, 3)).astype(np.uint8)  # 3 channels: new memory, the same values
    before = len(given)
    np.testing.assert_array_equal(p.map_to_frame(colour, False, alloc=alloc), p.map_to_frame(colour, False))
    assert len(given) == before


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


def test_frames_of_every_shape_are_written_into_the_slot_whole_between_bands_of_the_mean_colour():
    b = Boundary(tiny("thread"), {})
    mean_bgr = np.round(np.array([0.406, 0.456, 0.485]) * 255)
    rng = np.random.default_rng(2)
    # wide, tall (bands left and right), smaller (enlarged), odd sizes: a folder of images of every shape
    for h, w in [(100, 200), (100, 204), (240, 90), (61, 47), (120, 159)]:
        frame = rng.integers(0, 256, (h, w, 3), np.uint8)
        dst = np.full((120, 160, 3), 7, np.uint8)  # what an earlier frame left in the slot
        p = b.write(frame, dst)
        filt = cv2.INTER_AREA if min(w / p.w, h / p.h) >= 2 else cv2.INTER_LINEAR  # Note [Frame grid]
        inside = dst[p.y0 : p.y0 + p.h, p.x0 : p.x0 + p.w]
        np.testing.assert_array_equal(inside, cv2.resize(frame, (p.w, p.h), interpolation=filt))
        band = np.ones((120, 160), bool)
        band[p.y0 : p.y0 + p.h, p.x0 : p.x0 + p.w] = False
        assert band.any() and (dst[band] == mean_bgr).all(), (h, w)


def test_buffers_are_kept_for_a_bounded_number_of_sizes():
    cache: dict = {}
    first = buffer_for(cache, (10, 20), np.uint8)
    for i in range(SIZES_KEPT - 1):
        buffer_for(cache, (11 + i, 20), np.uint8)
    assert buffer_for(cache, (10, 20), np.uint8) is first  # used again: kept, now the most recent
    buffer_for(cache, (99, 99), np.uint8)  # one size too many: the least recently used goes, not the first
    assert (10, 20) in cache and (11, 20) not in cache and len(cache) == SIZES_KEPT


def fixed_capacity(boxes: list[list[float]], count: int, m: int = 6) -> dict[str, np.ndarray]:
    """A detection head's fixed-capacity outputs: ``count`` detections, 0 / -1 past them."""
    out = {
        "boxes": np.zeros((m, 4), np.float32),
        "scores": np.zeros(m, np.float32),
        "labels": np.full(m, -1, np.int32),
        "count": np.array(count, np.int32),
    }
    out["boxes"][: len(boxes)] = boxes
    out["scores"][:count] = np.linspace(0.9, 0.5, count)
    out["labels"][:count] = np.arange(count)
    return out


def test_boxes_mapped_into_the_band_are_dropped_with_their_rows_and_the_count_follows():
    """Note [Empty boxes]: a 300x1 frame fills one canvas row; boxes clipped to its edge have zero height."""
    from vpengine.engine.boundary import drop_empty_boxes

    p = Placement.fit((1, 300), (120, 160))  # region x 0..160, y 59..60
    canvas = [[0, 0, 16, 16], [16, 48, 32, 64], [0, 100, 160, 120], [40, 58, 80, 61], [5, 5, 5, 5]]
    kinds = {"boxes": "boxes"}
    out = fixed_capacity(canvas, count=4)  # the 5th is past count: padding, whatever it holds
    mapped = {**out, "boxes": p.boxes_to_frame(out["boxes"])}
    got = drop_empty_boxes(mapped, kinds)
    assert int(got["count"]) == 2 and got["count"].dtype == np.int32 and got["count"].shape == ()
    np.testing.assert_allclose(got["boxes"][:2], mapped["boxes"][[1, 3]])  # the kept ones, in their order
    np.testing.assert_allclose(got["scores"][:2], out["scores"][[1, 3]])
    assert got["labels"][:2].tolist() == [1, 3]
    assert got["boxes"].shape == (6, 4) and not got["boxes"][2:].any()  # shapes kept, padding past the count
    assert not got["scores"][2:].any() and (got["labels"][2:] == -1).all()
    assert all((b[2] > b[0]) and (b[3] > b[1]) for b in got["boxes"][:2])

    # the same as tensors, on their device, without leaving it
    t = {k: torch.from_numpy(np.asarray(v)) for k, v in mapped.items()}
    got_t = drop_empty_boxes(t, kinds)
    for k in ("boxes", "scores", "labels", "count"):
        np.testing.assert_array_equal(got_t[k].numpy(), got[k])

    # variable length (no count): the rows go
    var = {"boxes": mapped["boxes"][:4], "scores": out["scores"][:4], "labels": out["labels"][:4]}
    got_v = drop_empty_boxes(var, kinds)
    assert got_v["labels"].tolist() == [1, 3] and got_v["boxes"].shape == (2, 4)
    got_vt = drop_empty_boxes({k: torch.from_numpy(v) for k, v in var.items()}, kinds)
    assert got_vt["labels"].tolist() == [1, 3]


def test_outputs_without_empty_boxes_or_without_boxes_pass_as_they_are():
    from vpengine.engine.boundary import drop_empty_boxes

    out = fixed_capacity([[0, 0, 10, 10], [5, 5, 6, 7]], count=2)
    assert drop_empty_boxes(out, {"boxes": "boxes"}) is out
    depth = {"depth": np.zeros((120, 160), np.float32)}
    assert drop_empty_boxes(depth, {"depth": "map"}) is depth


def test_the_engine_returns_no_empty_box_for_frames_of_odd_shape():
    from vpengine.engine import Engine

    rng = np.random.default_rng(5)
    with Engine(tiny("thread", "heads.det.options.score_threshold=0.0")) as e:  # every cell a detection
        for hw in [(1, 1), (1, 300), (300, 1), (2, 3), (1080, 40)]:
            det = e.predict(rng.integers(0, 256, (*hw, 3), dtype=np.uint8))["det"]
            boxes = det["boxes"]
            assert len(boxes) == len(det["scores"]) == len(det["labels"]) == det["count"], hw
            assert ((boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])).all(), hw
            assert (boxes[:, [0, 2]] <= hw[1]).all() and (boxes[:, [1, 3]] <= hw[0]).all()


@pytest.mark.parametrize("as_tensor", [False, True])
def test_a_map_shrunk_to_a_third_is_averaged_and_one_shrunk_less_keeps_every_value_in_range(as_tensor):
    stripes = np.tile(np.array([0.0, 1.0], np.float32), (120, 80))  # one-pixel columns: the finest pattern there is
    m = torch.from_numpy(stripes) if as_tensor else stripes
    third = np.asarray(Placement.fit((40, 53), (120, 160)).map_to_frame(m, labels=False))
    assert third.shape == (40, 53)
    assert np.abs(third[:, 1:-1] - 0.5).max() < 0.2  # averaged: no stripes of 0s and 1s aliased into the frame
    less = np.asarray(Placement.fit((80, 107), (120, 160)).map_to_frame(m, labels=False))  # by 1.5: bilinear
    assert less.shape == (80, 107) and less.min() >= 0 and less.max() <= 1
    assert abs(float(less.mean()) - 0.5) < 0.05
    assert less.std() > 0.25  # bilinear keeps the stripes' contrast (area averaging would halve it: 0.14)
