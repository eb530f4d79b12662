"""Note [Building beside serving threads]: builds that overlap share one short switch interval and no full
collection, set by the first and undone after the last, whichever order they end in; what they made stays frozen
until the engines that built stop; a heap frozen by the program stays frozen."""

from __future__ import annotations

import gc
import sys
import threading
import weakref

import pytest

from helpers.builds import full_collections_can_be_held_off
from vpengine.runtime.threads import _NO_FULL_COLLECTION, BUILD_SWITCH_INTERVAL_S, _beside_serving, _builders

HOLDER = -1  # a runner's id() in the engine; any int here


generational = pytest.mark.skipif(not full_collections_can_be_held_off(), reason="an incremental collector")


@pytest.fixture(autouse=True)
def heap_unfrozen():
    assert not _builders.holders and _builders.count == 0, "a build or holder left by a test before"
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


def lasting_objects(n=200_000):
    """Objects that live on, as a build's graphs and kernels do: over ten collections of the middle generation."""
    return [[] for _ in range(n)]


def old_generation_empty():
    """A full collection due as soon as objects reach the old generation, whatever the heap's size: with the heap
    frozen and one collection run, the old generation is empty, so any object waiting for it is over its quarter."""
    gc.freeze()
    gc.collect()


@generational
@pytest.mark.parametrize("first_out", ["first", "second"])
def test_overlapping_builds_undo_what_they_changed_after_the_last(first_out):
    before = (sys.getswitchinterval(), gc.get_threshold())
    a, b = _beside_serving(HOLDER), _beside_serving(HOLDER)
    a.__enter__()
    b.__enter__()
    during = (sys.getswitchinterval(), gc.get_threshold(), gc.get_freeze_count() > 0)
    assert during == (BUILD_SWITCH_INTERVAL_S, (*before[1][:2], _NO_FULL_COLLECTION), True)
    (a if first_out == "first" else b).__exit__(None, None, None)
    assert (sys.getswitchinterval(), gc.get_threshold(), gc.get_freeze_count() > 0) == during
    (b if first_out == "first" else a).__exit__(None, None, None)
    assert (sys.getswitchinterval(), gc.get_threshold()) == before
    assert gc.get_freeze_count() > 0  # until the engine that built stops
    _builders.release(HOLDER)
    assert gc.get_freeze_count() == 0


@generational
def test_no_full_collection_runs_during_a_build_and_what_it_made_is_frozen_after_it():
    kept = []
    old_generation_empty()
    assert full_collections_while(lambda: kept.append(lasting_objects())) > 0  # without: the collector walks them
    gc.unfreeze()
    kept.clear()
    old_generation_empty()
    with _beside_serving(HOLDER):
        frozen = gc.get_freeze_count()
        assert full_collections_while(lambda: kept.append(lasting_objects())) == 0
    # no later full collection walks them either (a few frozen objects, the watcher's, are freed meanwhile)
    assert gc.get_freeze_count() >= frozen + len(kept[0]) - 100


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


def test_a_runner_already_stopping_holds_nothing():
    with _beside_serving(HOLDER, stopping=lambda: True):  # its stop released before this build came in
        assert HOLDER not in _builders.holders
    assert gc.get_freeze_count() == 0


def test_an_engine_finalised_by_a_collection_inside_releases_without_a_deadlock():
    """A collection inside (the builds' own, or one an allocation starts) may finalise an abandoned engine, whose
    stop releases its holder from the thread that holds the lock."""

    class Abandoned:
        pass

    def build():
        with _beside_serving(-2):
            cycle = Abandoned()
            cycle.me = cycle
            weakref.finalize(cycle, _builders.release, -2)
            del cycle

    t = threading.Thread(target=build, daemon=True)  # a deadlock fails the test, not the run
    t.start()
    t.join(10)
    assert not t.is_alive(), "the release from inside the collection waits for the lock its own thread holds"
    assert -2 not in _builders.holders  # released by the end's young collection, the lock held
    assert gc.get_freeze_count() == 0  # and the end's own check unfroze it: no holder left


def test_a_heap_the_program_froze_stays_frozen():
    gc.freeze()
    with _beside_serving(HOLDER):
        pass
    _builders.release(HOLDER)
    assert gc.get_freeze_count() > 0
