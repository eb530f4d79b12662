"""Note [Building beside serving threads]: builds that overlap share one short switch interval and no full
collection, set by the first and undone after the last, whichever order they end in; what they made stays frozen
until the engines that built stop; a heap frozen by the program stays frozen."""

from __future__ import annotations

import gc
import sys
import weakref

import pytest

from vpengine.runtime.threads import BUILD_SWITCH_INTERVAL_S, _beside_serving, _builders

HOLDER = -1  # a runner's id() in the engine; any int here


@pytest.fixture(autouse=True)
def heap_unfrozen():
    gc.unfreeze()  # a test before may have frozen it; these tests need to see what a build freezes
    yield
    _builders.release(HOLDER)
    gc.unfreeze()


def full_collections_while(make) -> int:
    """How many full (generation 2) collections ran while ``make()`` ran."""
    seen = []

    def watch(phase, info):
        if phase == "start" and info["generation"] == 2:
            seen.append(info)

    gc.callbacks.append(watch)
    try:
        make()
    finally:
        gc.callbacks.remove(watch)
    return len(seen)


def lasting_objects(n=300_000):
    """Objects that live on, as a build's graphs and kernels do: enough to call for full collections."""
    return [[] for _ in range(n)]


@pytest.mark.parametrize("first_out", ["first", "second"])
def test_overlapping_builds_undo_what_they_changed_after_the_last(first_out):
    before = (sys.getswitchinterval(), gc.get_threshold())
    a, b = _beside_serving(HOLDER), _beside_serving(HOLDER)
    a.__enter__()
    b.__enter__()
    during = (sys.getswitchinterval(), gc.get_threshold()[:2], gc.get_freeze_count() > 0)
    assert during == (BUILD_SWITCH_INTERVAL_S, before[1][:2], True)
    assert gc.get_threshold()[2] > 10**9  # no full collection
    (a if first_out == "first" else b).__exit__(None, None, None)
    assert (sys.getswitchinterval(), gc.get_threshold()[:2], gc.get_freeze_count() > 0) == during
    (b if first_out == "first" else a).__exit__(None, None, None)
    assert (sys.getswitchinterval(), gc.get_threshold()) == before
    assert gc.get_freeze_count() > 0  # until the engine that built stops
    _builders.release(HOLDER)
    assert gc.get_freeze_count() == 0


def test_no_full_collection_runs_during_a_build_and_what_it_made_is_frozen_after_it():
    kept = []
    assert full_collections_while(lambda: kept.append(lasting_objects())) > 0  # without: the collector walks them
    del kept[:]
    gc.collect()
    with _beside_serving(HOLDER):
        assert full_collections_while(lambda: kept.append(lasting_objects())) == 0
    assert gc.get_freeze_count() >= len(kept[0])  # no later full collection walks them either
    assert full_collections_while(lambda: kept.append(lasting_objects())) > 0  # young ones are collected as before
    assert gc.get_freeze_count() < len(kept[0]) + len(kept[1])


def test_a_builds_young_garbage_is_collected_not_frozen():
    class Node:
        pass

    with _beside_serving(HOLDER):
        a, b = Node(), Node()
        a.other, b.other = b, a  # a cycle: only the collector frees it
        gone = weakref.ref(a)
        del a, b
    assert gone() is None


def test_a_build_whose_engine_stopped_meanwhile_unfreezes_the_heap_when_it_ends():
    with _beside_serving(HOLDER):
        _builders.release(HOLDER)  # stop() gave up on the build: it still runs
        assert gc.get_freeze_count() > 0
    assert gc.get_freeze_count() == 0


def test_a_heap_the_program_froze_stays_frozen():
    gc.freeze()
    with _beside_serving(HOLDER):
        pass
    _builders.release(HOLDER)
    assert gc.get_freeze_count() > 0
