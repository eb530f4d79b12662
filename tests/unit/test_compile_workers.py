"""Note [Compile workers] in backends/compiled.py: a build beside serving threads waits for inductor's compile pool,
never longer than asked, and never past a stop. Inductor's pool is replaced by a future we control."""

import logging
import threading
import time
from concurrent.futures import Future

import pytest

from vpengine.backends.compiled import compile_workers_ready

async_compile = pytest.importorskip("torch._inductor.async_compile")


def test_inductor_still_has_what_the_wait_reads():
    """The wait reads torch's private pool state: a torch that renamed it fails here, not silently on a GPU."""
    assert callable(async_compile.AsyncCompile.use_process_pool)
    assert "_ready_future" in vars(async_compile.AsyncCompile)


@pytest.fixture
def pool(monkeypatch):
    """Inductor's pool as a future: ready once the future is done."""
    fut: Future = Future()
    monkeypatch.setattr(async_compile.AsyncCompile, "_ready_future", fut)
    monkeypatch.setattr(async_compile.AsyncCompile, "use_process_pool", classmethod(lambda cls: fut.done()))
    return fut


def test_a_pool_that_becomes_ready_is_waited_for(pool):
    threading.Timer(0.3, pool.set_result, ("ready",)).start()
    t0 = time.monotonic()
    assert compile_workers_ready(timeout_s=10.0)
    assert 0.2 < time.monotonic() - t0 < 5.0


def test_a_ready_pool_answers_at_once(pool):
    pool.set_result("ready")
    t0 = time.monotonic()
    assert compile_workers_ready(timeout_s=10.0)
    assert time.monotonic() - t0 < 1.0


def test_no_pool_is_no_wait(monkeypatch):
    """One compile thread (or no pool allowed): inductor never submits the pool's first job."""
    monkeypatch.setattr(async_compile.AsyncCompile, "_ready_future", None)
    monkeypatch.setattr(async_compile.AsyncCompile, "use_process_pool", classmethod(lambda cls: False))
    t0 = time.monotonic()
    assert not compile_workers_ready(timeout_s=10.0)
    assert time.monotonic() - t0 < 1.0


def test_a_slow_pool_is_given_up_on_with_a_warning(pool, caplog):
    with caplog.at_level(logging.WARNING, logger="vpengine.backends"):
        assert not compile_workers_ready(timeout_s=0.5)
    assert "not ready after" in caplog.text


def test_a_stop_ends_the_wait(pool):
    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    t0 = time.monotonic()
    assert not compile_workers_ready(timeout_s=30.0, cancelled=stop.is_set)
    assert time.monotonic() - t0 < 5.0


def test_a_pool_that_fails_while_waited_for_is_given_up_on(pool, caplog):
    threading.Timer(0.3, pool.set_exception, (RuntimeError("worker died"),)).start()
    with caplog.at_level(logging.WARNING, logger="vpengine.backends"):
        assert not compile_workers_ready(timeout_s=10.0)
    assert "worker died" in caplog.text


def test_a_pool_that_cannot_start_is_given_up_on(monkeypatch, caplog):
    def refuse(cls):
        raise OSError("no more processes")

    monkeypatch.setattr(async_compile.AsyncCompile, "use_process_pool", classmethod(refuse))
    with caplog.at_level(logging.WARNING, logger="vpengine.backends"):
        assert not compile_workers_ready(timeout_s=10.0)
    assert "no more processes" in caplog.text
