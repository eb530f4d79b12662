"""Borrowed results (``copy=False``): read-only views of a head's output slot, never written while referenced.

Each test runs in thread mode (local mailboxes) and process mode (shared memory written by other processes), on one
engine a mode that the tests share (a process-mode start takes seconds): each takes the engine as the one before
left it, with every result that test dropped collected, so its leases go back at the next call."""

from __future__ import annotations

import gc

import numpy as np
import pytest
import torch

from helpers.frames import frame
from tests_paths import tiny
from vpengine.engine import Engine

# one worker runs them all: the module's engines start once
pytestmark = [pytest.mark.timeout(300), pytest.mark.xdist_group("borrowed_results")]
MODES = ["thread", "process"]
SLOTS = 4 + 2  # output.slots (default) + the leases: frames after which an unpinned slot is overwritten


def snapshot(results):
    return {h: {k: np.array(v, copy=True) for k, v in r.outputs.items()} for h, r in results.items()}


def same(a, b):
    return a.keys() == b.keys() and all(
        a[h].keys() == b[h].keys() and all(np.array_equal(a[h][k], b[h][k]) for k in a[h]) for h in a
    )


def run_frames(e, first, n) -> list[int]:
    fids = []
    for i in range(first, first + n):
        fids.append(e.submit(frame(i)))
        e.wait(fids[-1], timeout=10)
    return fids


@pytest.fixture(scope="module", params=MODES)
def engine(request):
    with Engine(tiny(request.param)) as e:
        yield e


@pytest.fixture
def e(engine):
    gc.collect()  # what an earlier test dropped is garbage now: its leases go back at this test's first call
    return engine


def test_a_borrowed_result_equals_the_copy_is_read_only_and_never_changes(e):
    fid = e.submit(frame(0))
    copied = e.wait(fid, timeout=30)
    borrowed = e.wait(fid, timeout=30, copy=False)
    assert all(r.borrowed for r in borrowed.values()) and not any(r.borrowed for r in copied.values())
    assert same(snapshot(borrowed), snapshot(copied))
    assert borrowed["det"]["count"] == copied["det"]["count"]  # the head's finalize ran on the views
    depth = borrowed["depth"]["depth"]
    with pytest.raises(ValueError, match="read-only"):
        depth[0, 0] = 1.0
    kept = snapshot(borrowed)
    run_frames(e, 1, 3 * SLOTS)  # every other slot of every head is rewritten several times
    assert same(snapshot(borrowed), kept)
    assert e.stats()["results"]["depth"]["borrowed"] == 1


def test_a_view_or_tensor_keeps_its_slot_and_dropping_it_returns_the_lease(e):
    fid = e.submit(frame(0))
    res = e.wait(fid, timeout=30, copy=False)
    view = res["depth"]["depth"][..., 2:5]
    tensor = torch.from_numpy(np.asarray(res["seg"]["classes"]))
    want_view, want_tensor = view.copy(), tensor.clone()
    del res
    gc.collect()
    run_frames(e, 1, 3 * SLOTS)
    assert np.array_equal(view, want_view) and torch.equal(tensor, want_tensor)
    st = e.stats()["results"]
    assert (st["depth"]["borrowed"], st["seg"]["borrowed"], st["det"]["borrowed"]) == (1, 1, 0)
    del view, tensor
    e.wait(e.submit(frame(99)), timeout=10)  # the next call hands the leases back
    st = e.stats()["results"]
    assert (st["depth"]["borrowed"], st["seg"]["borrowed"]) == (0, 0)


def test_with_every_lease_out_results_are_copies_until_one_comes_back(e):
    held, fids = [], []  # two leases a head
    for i in range(3):
        fids.append(e.submit(frame(i)))
        held.append(e.wait(fids[-1], heads=["depth"], timeout=30, copy=False)["depth"])
    assert [r.borrowed for r in held] == [True, True, False]
    assert [r.frame_id for r in held] == fids
    assert e.stats()["results"]["depth"]["borrowed"] == 2
    del held[0]
    fid = e.submit(frame(3))
    again = e.wait(fid, heads=["depth"], timeout=30, copy=False)["depth"]
    assert again.borrowed and again.frame_id == fid
    # the latest() and results() paths lend too
    del again, held[:]
    assert e.latest("depth", copy=False).borrowed
    e.results()
    fids = run_frames(e, 4, 2)
    streamed = e.results(timeout=5, heads=["depth"], copy=False)
    assert [r.frame_id for r in streamed] == fids and all(r.borrowed for r in streamed)


def test_a_borrowed_result_outlives_the_engine():
    e = Engine(tiny("process")).start()
    try:
        res = e.wait(e.submit(frame(0)), timeout=30, copy=False)
        kept = snapshot(res)
    finally:
        e.stop()
    gc.collect()
    assert same(snapshot(res), kept)  # the shared mapping stays while a view of it does
