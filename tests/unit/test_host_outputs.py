"""Result arrays are recycled only when nothing refers to them any more: a kept result never changes."""

from __future__ import annotations

import threading
import types

import numpy as np
import pytest
import torch

from vpengine.engine.results import _RECYCLED_PER_OUTPUT, Outbox, _HostOutputs


def frame(i: int) -> np.ndarray:
    return np.full((4, 5), float(i), dtype=np.float32)


def test_a_dropped_array_is_reused_and_a_kept_one_never_changes():
    pool = _HostOutputs()
    a = pool.copy("depth", 0, "depth", frame(1))
    address = a.ctypes.data
    del a
    b = pool.copy("depth", 0, "depth", frame(2))
    assert b.ctypes.data == address and (b == 2).all()  # reused: no fresh memory for this frame
    c = pool.copy("depth", 0, "depth", frame(3))  # b is still held: c gets other memory
    assert c.ctypes.data != b.ctypes.data and (b == 2).all() and (c == 3).all()


def test_views_and_tensors_keep_their_array_alive():
    pool = _HostOutputs()
    view = pool.copy("det", 0, "boxes", frame(1))[1:3]  # the array itself is dropped, a view of it is kept
    tensor = torch.from_numpy(pool.copy("det", 0, "scores", frame(2)))
    for i in range(3, 3 + 2 * _RECYCLED_PER_OUTPUT):
        pool.copy("det", 0, "boxes", frame(i))
        pool.copy("det", 0, "scores", frame(i))
    assert (view == 1).all() and (tensor == 2).all()


def test_outputs_of_other_heads_or_shapes_are_not_mixed_up():
    pool = _HostOutputs()
    a = pool.copy("depth", 0, "depth", frame(1))
    del a
    seg = pool.copy("seg", 0, "depth", frame(7))  # same key name, other head: its own pool
    assert (seg == 7).all()
    small = pool.copy("depth", 0, "depth", np.ones((2, 2), np.float32))
    assert small.shape == (2, 2)
    big = pool.copy("depth", 0, "depth", np.zeros((8, 8), np.uint8))
    assert big.shape == (8, 8) and big.dtype == np.uint8


def test_the_pool_is_bounded_when_every_result_is_kept():
    pool = _HostOutputs()
    kept = [pool.copy("depth", 0, "depth", frame(i)) for i in range(10)]
    assert [int(k[0, 0]) for k in kept] == list(range(10))  # all distinct, none overwritten
    assert len(pool._pools["depth", 0, "depth"]) == _RECYCLED_PER_OUTPUT


def test_every_camera_of_a_tick_reuses_its_own_arrays():
    """A tick's results of eight cameras come out together; each camera's dropped arrays are reused on the next."""
    pool = _HostOutputs()
    tick = [pool.copy("depth", cam, "depth", frame(cam)) for cam in range(8)]
    addresses = [a.ctypes.data for a in tick]
    del tick
    for k in range(1, 4):
        tick = [pool.copy("depth", cam, "depth", frame(10 * k + cam)) for cam in range(8)]
        assert [a.ctypes.data for a in tick] == addresses  # no fresh memory: each camera's own array again
        assert [int(a[0, 0]) for a in tick] == [10 * k + cam for cam in range(8)]
        del tick


def test_a_camera_whose_frames_change_size_gets_arrays_of_the_new_size_kept():
    """Outputs mapped to the frame's grid take the frame's size: once a camera's frames change size, arrays of the
    new size are kept in place of the free ones of the old, and one still held keeps its content."""
    pool = _HostOutputs()
    kept = pool._pools.setdefault(("depth", 0, "depth"), [])
    held = pool.copy("depth", 0, "depth", frame(1))  # 4x5
    pool.copy("depth", 0, "depth", frame(2))  # dropped at once: free
    bigger = np.full((6, 7), 3.0, np.float32)
    a = pool.copy("depth", 0, "depth", bigger)
    assert any(x is a for x in kept)  # in place of the free 4x5 one
    new = id(a)  # the pool keeps it alive, so no other object has this id meanwhile
    del a
    b = pool.copy("depth", 0, "depth", bigger * 2)
    assert id(b) == new and (b == 6).all()  # the new size is kept and reused
    assert sorted(x.shape for x in kept) == [(4, 5), (6, 7)]
    assert (held == 1).all()


def test_one_odd_frame_does_not_keep_its_arrays_for_good():
    """A free array of a size no longer asked for goes as soon as one of the size asked for is reused: one big frame
    among small ones does not hold its outputs' memory for the engine's life."""
    pool = _HostOutputs()
    kept = pool._pools.setdefault(("depth", 0, "depth"), [])
    for i in range(2):
        pool.copy("depth", 0, "depth", frame(i))  # both dropped
    pool.copy("depth", 0, "depth", np.zeros((60, 80), np.float32))  # the odd one, dropped
    assert sorted(x.shape for x in kept) == [(4, 5), (60, 80)]
    pool.copy("depth", 0, "depth", frame(3))
    assert [x.shape for x in kept] == [(4, 5)]


def test_a_failed_copy_waits_for_the_other_heads_copies():
    """The caller releases the pinned slots as soon as ``_copy_out`` raises; a head's copy still reading its slot
    then would read a slot being written again."""
    outbox = Outbox.__new__(Outbox)  # only what _copy_out uses
    outbox.heads = {"depth": None, "seg": None}
    outbox._pool = None
    reading, finished = threading.Event(), threading.Event()

    def to_result(head, slot):
        if head == "depth":
            reading.set()
            threading.Event().wait(0.3)  # still copying
            finished.set()
            return head
        reading.wait(5)
        raise RuntimeError("seg's copy failed")

    outbox._to_result = to_result
    big = types.SimpleNamespace(tensors={"x": torch.zeros(1 << 20)})  # 4 MB: copied by the pool, not inline
    with pytest.raises(RuntimeError, match="seg's copy failed"):
        outbox._copy_out([("seg", big), ("depth", big)])  # seg's error is collected first
    assert finished.is_set()
    outbox._pool.shutdown()
