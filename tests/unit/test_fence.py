"""Note [Unmapping at stop]: the fence's users, its close, and defer's wait for the uses begun before it only."""

from __future__ import annotations

import threading

import pytest

from vpengine.runtime.fence import MappingFence
from vpengine.runtime.supervisor import EngineDeadError


def test_defer_waits_for_the_uses_begun_before_it_and_not_for_later_ones():
    fence, ran = MappingFence(), []
    inside, go = threading.Event(), threading.Event()

    def early_user():
        with fence:
            inside.set()
            go.wait(10)

    t = threading.Thread(target=early_user)
    t.start()
    inside.wait(10)
    fence.defer(lambda: ran.append("early"))
    assert ran == []  # a use begun before it may hold what it unmaps
    with fence:  # a use begun after it cannot: it neither waits for it nor is waited for
        pass
    assert ran == []
    go.set()
    t.join(10)
    assert ran == ["early"]
    fence.defer(lambda: ran.append("now"))  # nobody inside: at once
    assert ran == ["early", "now"]


def test_close_unmaps_when_the_last_use_ends_and_runs_what_was_deferred_first():
    fence, ran = MappingFence(), []
    fence.__enter__()
    fence.defer(lambda: ran.append("mailbox"))
    fence.close(lambda: ran.append("engine"))
    assert ran == []
    with pytest.raises(EngineDeadError):
        fence.__enter__()
    assert not fence.enter()
    fence.leave()
    assert ran == ["mailbox", "engine"]
