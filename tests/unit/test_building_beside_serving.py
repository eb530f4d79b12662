"""Note [Building beside serving threads]: builds that overlap share one short switch interval and one frozen heap,
set by the first and undone after the last, whichever order they end in; a heap frozen by the program stays frozen."""

from __future__ import annotations

import gc
import sys

import pytest

from vpengine.runtime.threads import BUILD_SWITCH_INTERVAL_S, ThreadRunner


def beside_serving():
    return ThreadRunner.beside_serving(None)  # type: ignore[arg-type]  # it reads nothing of the runner


@pytest.mark.parametrize("first_out", ["first", "second"])
def test_overlapping_builds_undo_what_they_changed_after_the_last(first_out):
    before = sys.getswitchinterval()
    a, b = beside_serving(), beside_serving()
    a.__enter__()
    b.__enter__()
    assert (sys.getswitchinterval(), gc.get_freeze_count() > 0) == (BUILD_SWITCH_INTERVAL_S, True)
    (a if first_out == "first" else b).__exit__(None, None, None)
    assert (sys.getswitchinterval(), gc.get_freeze_count() > 0) == (BUILD_SWITCH_INTERVAL_S, True)
    (b if first_out == "first" else a).__exit__(None, None, None)
    assert (sys.getswitchinterval(), gc.get_freeze_count()) == (before, 0)


def test_a_heap_the_program_froze_stays_frozen():
    gc.freeze()
    try:
        frozen = gc.get_freeze_count()
        young = [[] for _ in range(1000)]  # tracked, not frozen: a freeze inside would take them too
        with beside_serving():
            pass
        # neither unfrozen nor frozen again; other threads (a previous test's, ending) may free a few frozen objects
        assert frozen - len(young) < gc.get_freeze_count() <= frozen
    finally:
        gc.unfreeze()
