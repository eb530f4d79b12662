"""RecentFrames: the one store of recent input frames (and a tag each) by engine frame id."""

from __future__ import annotations

import numpy as np
import pytest

from vpengine.recent_frames import RecentFrames


def image(v: int) -> np.ndarray:
    return np.full((2, 3, 3), v, np.uint8)


def test_the_newest_frames_and_tags_are_kept_and_older_ones_forgotten():
    book: RecentFrames[str] = RecentFrames(frames=2, tags=3)
    for fid in range(4):
        book.add(fid, f"name{fid}", image(fid))
    assert [book.tag(f) for f in range(4)] == [None, "name1", "name2", "name3"]
    assert [book.frame(f) is None for f in range(4)] == [True, True, False, False]
    assert book.frame(3)[0, 0, 0] == 3 and book.frame(99) is None and book.tag(99) is None


def test_tags_alone_when_no_frames_are_kept():
    book: RecentFrames[int] = RecentFrames(frames=0, tags=2)
    assert not book.keeps_frames
    book.add(5, 50, image(5))
    assert book.tag(5) == 50 and book.frame(5) is None
    assert RecentFrames(frames=4).keeps_frames


def test_tags_default_to_as_many_as_frames():
    book: RecentFrames[str] = RecentFrames(frames=2)
    for fid in range(3):
        book.add(fid, str(fid), image(fid))
    assert book.tag(0) is None and book.tag(1) == "1" and book.frame(1) is not None


@pytest.mark.parametrize(("frames", "tags"), [(-1, 4), (4, 0)])
def test_bad_bounds_are_refused_naming_them(frames, tags):
    with pytest.raises(ValueError, match=f"got {frames} and {tags}"):
        RecentFrames(frames, tags)
