"""Frames of any size through the Engine API (thread mode): outputs in the submitted frame's pixel grid, the same
frame treated the same whatever its door (Note [Frame grid] in engine/boundary.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from helpers.frames import frame
from tests_paths import MEDIA, tiny
from vpengine.engine import Engine


@pytest.fixture(scope="module")
def engine():
    with Engine(tiny("thread")) as e:  # the models run at 160x120
        yield e


@pytest.mark.parametrize("hw", [(120, 160), (576, 768), (1080, 1920), (50, 300), (300, 90)])
def test_outputs_come_back_at_the_frame_size(engine, hw):
    out = engine.predict(frame(3, *hw))
    assert set(out) == {"depth", "seg", "det"}
    h, w = hw
    assert out["depth"]["depth"].shape == (h, w) and out["depth"]["depth"].dtype == np.float32
    assert out["seg"]["classes"].shape == (h, w) and out["seg"]["classes"].dtype == np.uint8
    boxes = out["det"]["boxes"]
    assert len(boxes) == out["det"]["count"] > 0
    assert (boxes[:, [0, 2]] <= w).all() and (boxes[:, [1, 3]] <= h).all() and (boxes >= 0).all()
    for r in out.values():
        assert r.frame_size == hw and r.grid == "frame" and r.image is not None
        assert r.plot().shape == (h, w, 3)


def test_a_frame_scaled_up_gives_the_outputs_of_the_frame_scaled_up(engine):
    small = frame(5)
    big = cv2.resize(small, (640, 480), interpolation=cv2.INTER_NEAREST)  # each pixel 4x4: shrinks back exactly
    a, b = engine.predict(small), engine.predict(big)
    np.testing.assert_allclose(
        b["depth"]["depth"], cv2.resize(a["depth"]["depth"], (640, 480), interpolation=cv2.INTER_LINEAR), rtol=1e-5
    )
    want = cv2.resize(a["seg"]["classes"], (640, 480), interpolation=cv2.INTER_NEAREST_EXACT)
    assert (b["seg"]["classes"] == want).mean() > 0.999
    np.testing.assert_allclose(b["det"]["boxes"], a["det"]["boxes"] * 4, atol=1e-3)


def test_a_native_grid_head_keeps_the_models_grid_and_says_so():
    with Engine(tiny("thread", "heads.depth.output.grid=native")) as e:
        out = e.predict(frame(1, 240, 640))
        assert out["depth"].grid == "native" and out["depth"]["depth"].shape == (120, 160)
        p = out["depth"].placement
        assert p.frame_hw == (240, 640) and (p.x0, p.y0, p.w, p.h) == (0, 30, 160, 60)
        assert out["seg"].grid == "frame" and out["seg"]["classes"].shape == (240, 640)


@pytest.mark.parametrize("hw", [(240, 320), (1080, 1920)])  # 1080p: the heads' outputs are copied side by side
def test_results_of_another_size_reuse_the_arrays_a_caller_let_go(engine, hw):
    """Outputs mapped to the frame's grid are written into the engine's recycled arrays (Note [Frame grid]): no new
    memory on every frame once the caller has dropped a result, and a result still held never changes."""
    pools = engine._outbox._host_outputs._pools

    def recycled(res, head, key):  # the array is one the engine keeps for reuse
        return any(res[head][key] is a for a in pools.get((head, 0, key), []))

    first = engine.wait(engine.submit(frame(1, *hw)), timeout=5)
    held, kept = first["depth"]["depth"], first["depth"]["depth"].copy()
    assert recycled(first, "depth", "depth") and recycled(first, "seg", "classes")
    seg = id(first["seg"]["classes"])
    del first
    for i in (2, 3):
        res = engine.wait(engine.submit(frame(i, *hw)), timeout=5)
        assert id(res["seg"]["classes"]) == seg and res["seg"]["classes"].shape == hw  # the one let go
        assert recycled(res, "depth", "depth") and res["depth"]["depth"] is not held
        assert not np.array_equal(res["depth"]["depth"], kept)  # another frame, other values
        del res
    np.testing.assert_array_equal(held, kept)  # held: never reused


def test_borrowed_results_of_another_size_are_copies_in_the_frame_grid_said_once_a_head(engine, caplog):
    import logging

    engine._outbox._told_not_lent.clear()  # whatever another test of this module's engine did first

    with caplog.at_level(logging.WARNING, "vpengine"):
        for _ in range(2):
            fid = engine.submit(frame(2, 240, 320))
            r = engine.wait(fid, copy=False, timeout=5)["depth"]
            assert not r.borrowed and r["depth"].shape == (240, 320)
    said = [m for m in caplog.messages if "copy=False results are copies" in m]
    assert sorted(m.split(":")[0] for m in said) == ["depth", "det", "seg"], said  # once a head, not once a frame
    assert "the frame (320x240) is not the models' input size" in said[0]
    fid = engine.submit(frame(2))
    assert engine.wait(fid, copy=False, timeout=5)["depth"].borrowed


def test_the_readme_frame_slot_snippet_on_the_street_video(engine):
    cap = cv2.VideoCapture(str(MEDIA / "vtest.avi"))
    h, w = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)), int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
    with engine.frame_slot(size=(h, w)) as slot:
        ok, slot.array = cap.read(image=slot.array)
        if not ok:
            slot.cancel()
    out = engine.wait(slot.frame_id, timeout=5)
    assert out["depth"]["depth"].shape == (576, 768)
    # the same frame submitted gives the same outputs
    cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
    _, img = cap.read()
    again = engine.predict(img)
    np.testing.assert_array_equal(again["depth"]["depth"], out["depth"]["depth"])


def test_a_writer_that_reallocates_instead_of_writing_into_the_slot_is_refused(engine):
    cap = cv2.VideoCapture(str(MEDIA / "vtest.avi"))
    before = engine.stats()["engine"]["submitted"]
    refused = pytest.raises(
        ValueError,
        match=r"the frame written is \(576, 768, 3\) uint8, the slot \(120, 160, 3\) uint8: a writer that cannot "
        r"write into the slot allocated a new array, and nothing reached the slot; open the slot with frame_slot\(size",
    )
    with refused, engine.frame_slot() as slot:  # the models' size, not the video's
        _, slot.array = cap.read(image=slot.array)
    assert engine.stats()["engine"]["submitted"] == before  # nothing (no zero frame) went in
    refused = pytest.raises(ValueError, match=r"the frame written is \(60, 160, 3\) uint8, the slot \(120, 160, 3\)")
    with refused, engine.frame_slot() as slot:
        slot.array = slot.array[:60]  # same memory, another shape
    # the same size but another dtype: not a size to change (the reason a reviewer found misnamed)
    dtype = pytest.raises(ValueError, match=r"\(120, 160, 3\) float32, the slot \(120, 160, 3\) uint8: .*slot$")
    with dtype, engine.frame_slot() as slot:
        slot.array = slot.array.astype(np.float32)
    # the same shape and dtype, another array: written elsewhere
    elsewhere = pytest.raises(ValueError, match=r"written into another 160x120 uint8 array, not into the slot")
    with elsewhere, engine.frame_slot() as slot:
        slot.array = slot.array.copy()
    for bad in ("640x480", (1, 2, 3), (10.7, 20.2), (True, 5)):
        with pytest.raises(ValueError, match=r"frame_slot size must be \(height, width\) in whole pixels"):
            engine.frame_slot(size=bad)
    with engine.frame_slot(size=(240.0, 320.0)) as slot:  # as OpenCV's CAP_PROP_FRAME_HEIGHT gives a size
        assert slot.array.shape == (240, 320, 3)
        slot.cancel()
    fid = engine.submit(frame(1))
    assert set(engine.wait(fid, timeout=5)) == {"depth", "seg", "det"}


def test_plot_draws_rgb_and_float_frames_as_bgr_pictures_and_native_results_in_the_frames_grid():
    """Result.plot draws a BGR uint8 picture whatever the input's colour order and dtype, and a result kept in the
    models' grid (output.grid: native) is drawn where it lies on the frame, not stretched or in a corner."""
    img = frame(3, 240, 320)
    with Engine(tiny("thread")) as bgr:
        want = bgr.predict(img)["det"].plot()  # the default input: BGR uint8
    rgb_img = np.ascontiguousarray(img[..., ::-1])
    with Engine(tiny("thread", "input.color=rgb")) as rgb:
        r = rgb.predict(rgb_img)["det"]
        np.testing.assert_array_equal(r.image, img)  # the picture is BGR
    with Engine(tiny("thread", "input.dtype=float32")) as flt:
        pic = flt.predict(img.astype(np.float32) / 255)["det"].plot()  # drew nothing before: cv2 refused float
        assert pic.dtype == np.uint8 and pic.shape == (240, 320, 3)
        with pytest.raises(ValueError, match=r"with values 0..1; got values up to 255 \(divide by 255\)"):
            flt.submit(img.astype(np.float32))
    grids = [f"heads.{h}.output.grid=native" for h in ("depth", "seg")]
    wide = frame(4, 180, 320)  # 16:9 into the models' 4:3: letterboxed, so stretching is not mapping
    with Engine(tiny("thread", *grids)) as native:
        out = native.predict(wide)
        for head in ("depth", "seg"):
            assert out[head][next(iter(out[head].outputs))].shape == (120, 160)  # kept in the models' grid
            with Engine(tiny("thread")) as framed:
                drawn = framed.predict(wide)[head].plot()
            # drawn in the frame's grid, as the same head's frame-grid result is
            assert np.abs(out[head].plot().astype(int) - drawn.astype(int)).mean() < 8, head
    assert want.shape == (240, 320, 3)
