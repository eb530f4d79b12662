"""Frame sources. A camera is a stand-in capture the test hands frames to one at a time (Note [Live capture])."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest

from helpers.camera import FakeCamera
from vpengine.io.sources import VideoSource


def wait_until(cond: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


def camera_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "vpengine-camera"]


def test_a_loop_that_keeps_up_with_the_camera_gets_every_frame_in_order():
    cam = FakeCamera()
    src = VideoSource(0, capture=cam)
    assert src.live and (src.width, src.height, src.fps) == (8, 6, 30.0) and len(src) == 0
    it = iter(src)
    for k in range(6):
        cam.deliver()
        f = next(it)
        assert f.name == f"{k:06d}" and int(f.image[0, 0, 0]) == k and f.timestamp is not None
    assert src.missed == 0
    cam.end_at = cam.i  # unplugged: the frames end
    cam.deliver()
    assert list(it) == []
    wait_until(lambda: not camera_threads())


def test_a_slow_loop_takes_the_newest_frame_and_counts_the_ones_it_replaced():
    cam = FakeCamera()
    src = VideoSource(0, capture=cam)
    it = iter(src)
    cam.deliver()
    assert next(it).name == "000000"  # the reader thread runs from here on
    cam.deliver(5)  # five frames come while the loop is busy
    wait_until(lambda: src.missed == 4)
    f = next(it)
    assert f.name == "000005" and int(f.image[0, 0, 0]) == 5  # the newest, not the oldest queued
    cam.deliver()
    assert next(it).name == "000006" and src.missed == 4
    cam.end_at = cam.i
    cam.deliver()
    assert list(it) == []
    wait_until(lambda: not camera_threads())


def test_the_camera_ending_ends_the_frames_after_the_newest_and_every_frame_is_taken_or_counted():
    cam = FakeCamera(end_at=9)
    src = VideoSource(0, capture=cam)
    cam.deliver(10)  # nine frames, then the end
    frames = list(src)
    ids = [int(f.name) for f in frames]
    assert ids == sorted(set(ids)) and ids[-1] == 8 and len(ids) + src.missed == 9
    wait_until(lambda: not camera_threads())


def test_a_camera_that_fails_raises_naming_it_and_stopping_early_stops_its_reader():
    cam = FakeCamera(fail_at=2)
    cam.deliver(3)
    with pytest.raises(RuntimeError, match=r"reading camera 0 failed: OSError\('device unplugged'\)"):
        list(VideoSource(0, capture=cam))
    wait_until(lambda: not camera_threads())

    cam = FakeCamera()
    it = iter(VideoSource(0, capture=cam))
    cam.deliver()
    next(it)
    it.close()  # type: ignore[attr-defined]  # waits up to 1 s for the read in progress
    cam.deliver()  # which returns with the camera's next frame, and the reader stops there
    wait_until(lambda: not camera_threads())
    assert cam.i == 2


# ------------------------------------------------------------------------------------------------ images, specs
def write_images(folder, sizes, ext: str = "png") -> list:
    import cv2
    import numpy as np

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, (h, w) in enumerate(sizes):
        img = np.zeros((h, w, 3), np.uint8)
        img[:, : w // 2] = (10 * i, 100, 200)  # left half coloured: a stretched image would move the edge
        paths.append(folder / f"im{i}.{ext}")
        assert cv2.imwrite(str(paths[-1]), img)
    return paths


def test_a_folder_of_mixed_sizes_gives_each_image_at_its_own_size_stamped_on_the_folders_timeline(tmp_path):
    from vpengine.io.sources import open_source

    sizes = [(60, 80), (1080, 1920), (33, 47), (480, 640)]
    write_images(tmp_path / "f", sizes)
    with open_source(str(tmp_path / "f")) as src:
        assert (src.height, src.width) == (60, 80) and len(src) == 4  # the first image's size
        frames = list(src)
    assert [f.image.shape for f in frames] == [(h, w, 3) for h, w in sizes]
    for f, (_, w) in zip(frames, sizes):  # never stretched: the coloured half ends where it did
        assert (f.image[:, : w // 2, 1] == 100).all() and not f.image[:, w // 2 :].any()
    assert [f.name for f in frames] == ["im0", "im1", "im2", "im3"]
    assert [f.timestamp for f in frames] == pytest.approx([0, 1 / 30, 2 / 30, 3 / 30])  # 30 Hz unless told
    with open_source(str(tmp_path / "f"), fps=4) as src:
        assert [f.timestamp for f in src] == [0, 0.25, 0.5, 0.75]


def test_a_single_image_and_a_glob_are_sources(tmp_path):
    from vpengine.io.sources import open_source

    paths = write_images(tmp_path / "a", [(40, 50), (20, 30)])
    write_images(tmp_path / "b", [(10, 20)], ext="jpg")
    with open_source(str(paths[1])) as src:
        assert [(f.name, f.image.shape) for f in src] == [("im1", (20, 30, 3))]
    with open_source(str(tmp_path / "a" / "*.png")) as src:
        assert [f.name for f in src] == ["im0", "im1"]
    with open_source(str(tmp_path / "**" / "im0.*")) as src:  # the same name in two folders stays two names
        assert [f.name for f in src] == ["000000_im0", "000001_im0"]
    with pytest.raises(ValueError, match=r"no images .* match '.*\*\.bmp'"):
        open_source(str(tmp_path / "a" / "*.bmp"))


def test_an_unreadable_image_is_skipped_and_listed_and_a_truncated_one_is_used_with_a_warning(tmp_path, caplog):
    import cv2
    import numpy as np

    from vpengine.io.sources import open_source

    folder = tmp_path / "f"
    write_images(folder, [(40, 50)] * 3)
    (folder / "im1.png").write_bytes(b"this is no image")
    rng = np.random.default_rng(0)
    assert cv2.imwrite(str(folder / "im3.jpg"), rng.integers(0, 256, (64, 64, 3), dtype=np.uint8))
    data = (folder / "im3.jpg").read_bytes()
    (folder / "im3.jpg").write_bytes(data[: len(data) // 2])  # cut in half: the decoder fills in the rest
    png = (folder / "im2.png").read_bytes()
    (folder / "im4.png").write_bytes(png[: len(png) - 20])  # a PNG cut short does not decode at all
    with caplog.at_level("WARNING", logger="vpengine.sources"), open_source(str(folder)) as src:
        frames = list(src)
    assert [f.name for f in frames] == ["im0", "im2", "im3"]
    assert frames[2].image.shape == (64, 64, 3)
    assert src.skipped == [
        {"file": str(folder / "im1.png"), "why": "not a readable image"},
        {"file": str(folder / "im4.png"), "why": "not a readable image"},
    ]
    assert src.partial == [str(folder / "im3.jpg")]
    assert "im3.jpg is truncated: decoded partially" in caplog.text and "skipping" in caplog.text

    write_images(tmp_path / "g", [(40, 50)])
    (tmp_path / "g" / "im0.png").write_bytes(b"")
    with pytest.raises(ValueError, match="none of the 1 images .* can be read"):
        open_source(str(tmp_path / "g"))


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("synthetic:64x64@0", "synthetic source rate must be a number of Hz above 0, got 0.0"),
        ("synthetic:64x64@0.0:3", "synthetic source rate must be a number of Hz above 0, got 0.0"),
        ("synthetic:64x64@.", "bad synthetic source"),
        ("camera:front", "use camera:N with N the camera's index"),
        ("sample:nope", "no sample named 'nope'; samples: cheetah, street"),
        ("no/such/file.avi", "does not exist .*sample:NAME"),
    ],
)
def test_bad_source_specs_are_refused_with_what_is_accepted(spec, message):
    from vpengine.io.sources import open_source

    with pytest.raises(ValueError, match=message):
        open_source(spec)


def test_the_shipped_samples_are_sources():
    from vpengine.io.sources import open_source

    with open_source("sample:cheetah") as src:
        (frame,) = list(src)
        assert frame.image.shape == (1080, 1920, 3) and frame.name == "cheetah" and frame.image.mean() > 10
    with open_source("sample:street") as src:
        assert (src.width, src.height, src.fps, len(src)) == (768, 576, 10.0, 50)
        stamps = [f.timestamp for f in src]
    assert len(stamps) == 50 and stamps[:3] == pytest.approx([0.0, 0.1, 0.2])  # the video's own timeline


def test_what_a_pipeline_reads_has_a_default_on_every_source():
    from vpengine.io.base import Source
    from vpengine.io.sources import SyntheticSource

    class Frames(Source):
        def __iter__(self):
            return iter(())

    plain = Frames()
    assert (plain.live, plain.missed, list(plain.skipped), list(plain.partial), plain.header_for) == (
        False,
        0,
        [],
        [],
        None,
    )
    assert plain.pace == "lockstep" and plain.describe() == "Frames"
    synthetic = SyntheticSource(32, 24, 30.0, 3)
    assert synthetic.pace == "realtime" and not synthetic.live  # paced like a camera, by the pipeline
    camera = VideoSource(0, FakeCamera())
    assert camera.live and camera.pace == "realtime"
    camera.close()
    stream = VideoSource("https://user:secret@example.com/v.mp4", FakeCamera(), live=False)
    assert stream.pace == "lockstep" and "secret" not in stream.describe()
    stream.close()


# ------------------------------------------------------------------------------------------------ short videos
def write_video(path, frames: int = 30) -> bytes:
    """A small MJPG AVI of noise (every frame a full JPEG, so a cut one ends at a frame), its bytes returned."""
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48))
    assert w.isOpened()
    for _ in range(frames):
        w.write(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    w.release()
    return path.read_bytes()


def test_a_video_cut_short_ends_with_a_warning_naming_it_and_is_listed_as_partial(tmp_path, caplog):
    from vpengine.io.sources import open_source

    data = write_video(tmp_path / "whole.avi")
    (tmp_path / "cut.avi").write_bytes(data[: len(data) // 2])  # its header still announces 30 frames
    with caplog.at_level("WARNING", logger="vpengine.sources"), open_source(str(tmp_path / "cut.avi")) as src:
        assert len(src) == 30
        n = len(list(src))
    assert 0 < n < 28 and src.partial == [str(tmp_path / "cut.avi")]
    (line,) = [r.getMessage() for r in caplog.records]
    assert f"video '{tmp_path / 'cut.avi'}' ended after {n} of the 30 frames its header announces" in line

    caplog.clear()
    with caplog.at_level("WARNING", logger="vpengine.sources"), open_source(str(tmp_path / "whole.avi")) as src:
        assert len(list(src)) == 30
    assert src.partial == [] and caplog.records == []


class CountedClip(FakeCamera):
    """A stand-in video file whose header announces ``announced`` frames."""

    def __init__(self, announced: int, end_at: int) -> None:
        super().__init__(end_at=end_at)
        self.announced = announced
        self.deliver(end_at + 1)  # a file: every frame there at once

    def get(self, prop: int) -> float:
        import cv2

        return float(self.announced) if prop == cv2.CAP_PROP_FRAME_COUNT else super().get(prop)


@pytest.mark.parametrize(
    ("announced", "frames", "short"),
    [(40, 40, False), (40, 39, False), (40, 38, False), (40, 37, True), (40, 0, True), (400, 380, False),
     (400, 379, True)],
)  # fmt: skip
def test_a_video_is_short_only_when_it_ends_over_two_frames_and_5_percent_before_its_count(
    announced, frames, short, caplog
):
    # headers are approximate (Note [Short videos]): a frame or two missing, or a few percent, is no damage
    src = VideoSource("clip.mp4", CountedClip(announced=announced, end_at=frames), live=False)
    with caplog.at_level("WARNING", logger="vpengine.sources"):
        assert len(list(src)) == frames
    assert src.partial == (["clip.mp4"] if short else [])
    assert (f"ended after {frames} of the {announced} frames" in caplog.text) is short


def test_a_short_video_at_a_url_is_listed_without_its_password(caplog):
    src = VideoSource(
        "https://user:secret@example.com/clip.mp4", CountedClip(announced=40, end_at=10), live=False,
        what="video 'https://user:***@example.com/clip.mp4'",
    )  # fmt: skip
    with caplog.at_level("WARNING", logger="vpengine.sources"):
        assert len(list(src)) == 10
    assert src.partial == ["https://user:***@example.com/clip.mp4"] and "secret" not in caplog.text
