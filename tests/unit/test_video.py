"""Note [Browser video] (io/video.py): ``--video`` writes what browsers play, H.264 in mp4 where an encoder is
there, and says so plainly where none is. Codecs are read from the file itself (the mp4 'stsd' box, WebM's codec
id), not from a tool."""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from vpengine.engine.results import Result
from vpengine.io import video
from vpengine.io.sinks import AnnotatedSink

HEADS = {"depth": {"kind": "depth"}}


def mp4_codec(path: Path) -> str:
    """The first sample entry's format in the mp4's 'stsd' box: 'avc1' is H.264, 'mp4v' MPEG-4 Part 2."""
    data = path.read_bytes()
    i = data.find(b"stsd")
    assert i > 0, "no stsd box: not an mp4"
    # 'stsd', version and flags (4), entry count (4), the entry's size (4), then its format
    return data[i + 16 : i + 20].decode("ascii")


def write_frames(path: Path, hw: tuple[int, int], n: int = 3) -> AnnotatedSink:
    sink = AnnotatedSink(HEADS, video=path, fps=10)
    rng = np.random.default_rng(0)
    for i in range(n):
        depth = rng.random(hw).astype(np.float32)
        sink.write(Result("depth", i, i / 10, 0.01, {"depth": depth}), np.full((*hw, 3), 40 * i, np.uint8), f"f{i}")
    sink.close()
    return sink


def read_back(path: Path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f)
    cap.release()
    return frames


@pytest.mark.parametrize("hw", [(60, 80), (1, 1), (1, 300), (300, 1), (2, 3)])
def test_the_video_is_h264_in_mp4_at_an_even_size_for_a_frame_of_any_shape(tmp_path, hw):
    av = pytest.importorskip("av", reason="the H.264 encoder comes with vpengine[video] (PyAV)")
    if "libx264" not in av.codecs_available and "libopenh264" not in av.codecs_available:
        pytest.skip("this PyAV has no H.264 encoder")
    path = tmp_path / "v.mp4"
    write_frames(path, hw)
    assert mp4_codec(path) == "avc1"  # H.264: what every browser plays
    frames = read_back(path)
    assert len(frames) == 3 and frames[0].shape[0] % 2 == 0 and frames[0].shape[1] % 2 == 0


def test_without_an_h264_encoder_the_mp4_is_mpeg4_part2_and_a_warning_says_how_to_get_one(
    tmp_path, monkeypatch, caplog
):
    monkeypatch.setitem(sys.modules, "av", None)  # PyAV not installed
    real = video._opencv_writer
    monkeypatch.setattr(
        video, "_opencv_writer", lambda p, fourcc, *a: None if fourcc == "avc1" else real(p, fourcc, *a)
    )
    path = tmp_path / "v.mp4"
    with caplog.at_level(logging.WARNING, logger="vpengine"):
        write_frames(path, (60, 80))
    assert mp4_codec(path) == "mp4v" and len(read_back(path)) == 3
    (line,) = [r.getMessage() for r in caplog.records]
    assert "which browsers do not play" in line and "pip install 'vpengine[video]'" in line and str(path) in line


def test_a_webm_name_gets_vp8(tmp_path):
    path = tmp_path / "v.webm"
    try:
        write_frames(path, (30, 40), n=2)
    except OSError as e:
        pytest.skip(str(e))  # an OpenCV without libvpx
    assert path.read_bytes()[:4] == b"\x1a\x45\xdf\xa3" and b"V_VP8" in path.read_bytes()  # EBML, codec id
    assert len(read_back(path)) == 2


def test_a_video_of_odd_size_is_refused_by_the_writer_itself(tmp_path):
    with pytest.raises(ValueError, match="video size must be even numbers of pixels .*, got 81x60"):
        video.VideoWriter(tmp_path / "v.mp4", 10, (81, 60))
    assert video.even_size(81, 59) == (82, 60) and video.even_size(2, 2) == (2, 2)


def test_opencvs_h264_is_probed_once_per_process_not_per_file(tmp_path, monkeypatch):
    # each borrowing of stderr (Note [Borrowing stderr]) swallows other threads' stderr too: once, not per video
    monkeypatch.setitem(sys.modules, "av", None)  # PyAV not installed: OpenCV writes
    monkeypatch.setattr(video, "_avc1", None, raising=False)  # not probed yet in this process
    borrowed = []
    real_dup2 = os.dup2

    def dup2(fd: int, fd2: int, inheritable: bool = True) -> int:
        if fd2 == 2:
            borrowed.append(fd)
        return real_dup2(fd, fd2, inheritable)

    monkeypatch.setattr(os, "dup2", dup2)
    for name in ("a.mp4", "b.mp4", "c.mp4"):
        write_frames(tmp_path / name, (60, 80))
    assert len(borrowed) == 2  # to a file and back, once
    assert all(mp4_codec(tmp_path / n) in ("avc1", "mp4v") for n in ("a.mp4", "b.mp4", "c.mp4"))


def test_a_video_is_written_by_a_process_without_a_stderr(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "av", None)
    monkeypatch.setattr(video, "_avc1", None, raising=False)

    def no_stderr(fd: int) -> int:
        raise OSError(9, "Bad file descriptor")

    monkeypatch.setattr(os, "dup", no_stderr)
    write_frames(tmp_path / "v.mp4", (60, 80))
    assert len(read_back(tmp_path / "v.mp4")) == 3


@pytest.mark.parametrize("name", ["v.gif", "v.ogv", "v.h264", "v"])
def test_a_name_that_is_no_video_the_writer_makes_is_refused_naming_it_and_the_accepted_ones(tmp_path, name):
    path = tmp_path / name
    with pytest.raises(ValueError) as e:
        video.VideoWriter(path, 10, (64, 48))
    assert str(e.value) == (
        f"video {str(path)!r}: cannot write a video as {repr(path.suffix) if path.suffix else 'no extension'}; "
        "name it .mp4, .avi, .m4v, .mkv, .mov, .webm (browsers play .mp4 and .webm)"
    )
    assert not path.exists()
    from vpengine.io.sinks import AnnotatedSink

    with pytest.raises(ValueError, match="cannot write a video as"):  # at construction, not at the first frame
        AnnotatedSink({}, video=path)


@pytest.mark.parametrize("name", ["v.avi", "v.m4v", "v.mkv", "v.mov", "V.MP4"])
@pytest.mark.parametrize("pyav", [True, False])
def test_every_accepted_name_is_written_and_reads_back_with_pyav_or_opencv_alone(tmp_path, monkeypatch, name, pyav):
    if not pyav:
        monkeypatch.setitem(sys.modules, "av", None)
    write_frames(tmp_path / name, (30, 40))
    assert len(read_back(tmp_path / name)) == 3
