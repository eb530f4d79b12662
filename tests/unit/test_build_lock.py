"""Note [One build at a time]: the process's build lock is held until a build returns, so nobody waits for it
blindly: a waiter gives up once it is no longer wanted or once the holder has made no progress for its timeout, and
the error and the log name the holder."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from helpers.builds import held_elsewhere, in_threads
from vpengine.models import build
from vpengine.models.build import BuildCancelled, BuildLock, BuildLockTimeout


@pytest.fixture
def busy():
    """A lock held by another thread, named 'builder', building "model 'slow'", until the test ends."""
    lock = BuildLock()
    with held_elsewhere(lock, "model 'slow'"):
        yield lock
    assert lock.holder() is None  # released with the build


def test_a_waiter_past_its_timeout_fails_naming_the_holder(busy):
    assert "model 'slow'" in busy.holder() and "'builder'" in busy.holder()
    t = time.monotonic()
    with pytest.raises(BuildLockTimeout) as e, busy.held("model 'depth'", 0.5):
        pass
    assert time.monotonic() - t < 5
    text = str(e.value)
    assert "model 'depth'" in text and "model 'slow'" in text and "'builder'" in text
    assert "no progress for runtime.ready_timeout_s = 0.5 s" in text
    assert not isinstance(e.value, ValueError)  # not the config's fault: a busy process


def test_a_waiter_waits_while_the_holder_makes_progress():
    """Note [Start progress]: a holder compiling step after step is slow, not stuck; the timeout counts from its
    last step (another thread's steps count for nothing), and once the steps stop the waiter gives up."""
    lock, stepping_for = BuildLock(), 2.0
    entered, release = threading.Event(), threading.Event()

    def build() -> None:
        with lock.held("model 'slow'", 5):
            entered.set()
            until = time.monotonic() + stepping_for
            while time.monotonic() < until:
                lock.step()
                time.sleep(0.1)
            release.wait(30)

    threading.Thread(target=build, name="builder", daemon=True).start()
    assert entered.wait(10)
    t = time.monotonic()
    try:
        with pytest.raises(BuildLockTimeout) as e, lock.held("model 'depth'", 1.0):
            pass
    finally:
        release.set()
    waited = time.monotonic() - t
    assert stepping_for <= waited < stepping_for + 6, waited  # twice its timeout, while the holder stepped
    assert "made no progress for runtime.ready_timeout_s = 1 s" in str(e.value)


def test_a_step_by_another_thread_does_not_hold_a_waiter(busy):
    t = time.monotonic()
    stop = threading.Event()

    def steps() -> None:
        while not stop.wait(0.05):
            busy.step()  # not the holder

    threading.Thread(target=steps, daemon=True).start()
    try:
        with pytest.raises(BuildLockTimeout), busy.held("model 'depth'", 0.5):
            pass
    finally:
        stop.set()
    assert time.monotonic() - t < 5


def test_a_waiter_no_longer_wanted_leaves_without_building(busy):
    wanted = threading.Event()
    wanted.set()
    ran = []
    out: list[BaseException] = []

    def wait() -> None:
        try:
            with busy.held("model 'depth'", 60, cancelled=lambda: not wanted.is_set()):
                ran.append(1)
        except BaseException as e:
            out.append(e)

    t = threading.Thread(target=wait, daemon=True)
    t.start()
    time.sleep(0.3)
    assert t.is_alive()  # waiting: the holder builds
    wanted.clear()  # e.g. its engine stopped
    t.join(10)
    assert not t.is_alive() and not ran
    assert len(out) == 1 and isinstance(out[0], BuildCancelled) and "model 'depth'" in str(out[0])


def test_a_long_wait_is_logged_once_with_the_holder(busy, monkeypatch, caplog):
    monkeypatch.setattr(build, "WAIT_LOG_S", 0.3)
    logged = caplog.at_level(logging.INFO, logger="vpengine.models.build")
    with logged, pytest.raises(BuildLockTimeout), busy.held("model 'depth'", 1.5):
        pass
    lines = [r.getMessage() for r in caplog.records if r.name == "vpengine.models.build"]
    assert len(lines) == 1, lines
    assert "model 'depth' waits" in lines[0] and "model 'slow'" in lines[0]


def test_builds_take_turns_and_a_free_lock_is_taken_at_once():
    lock = BuildLock()
    inside, overlap = [0], []

    def build_one() -> None:
        with lock.held("model 'x'", 30):
            inside[0] += 1
            overlap.append(inside[0])
            time.sleep(0.01)
            inside[0] -= 1

    in_threads(build_one, 8)
    assert overlap == [1] * 8  # never two at once
    t = time.monotonic()
    with lock.held("model 'y'", 30):
        assert lock.holder().startswith("model 'y'")
    assert time.monotonic() - t < 1


def test_an_error_in_a_build_lets_go_and_a_build_nobody_wants_never_starts():
    lock = BuildLock()
    with pytest.raises(RuntimeError, match="init failed"), lock.held("model 'x'", 5):
        raise RuntimeError("init failed")
    assert lock.holder() is None
    ran = []
    with pytest.raises(BuildCancelled, match="model 'y'"), lock.held("model 'y'", 5, cancelled=lambda: True):
        ran.append(1)  # the lock was free, but the build is no longer wanted
    assert not ran and lock.holder() is None
    with lock.held("model 'z'", 5):  # and the lock is free again
        pass
