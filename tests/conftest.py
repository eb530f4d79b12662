"""Shared fixtures. Every test is checked for leaks: no new /dev/shm entries, no child process left alive, Ctrl-C's
handler as the test found it."""

from __future__ import annotations

import os
import signal
import subprocess
import time

import psutil
import pytest

from helpers.leaks import shm_held_by
from tests_paths import DEVICE, ROOT


def _children() -> set[int]:
    """This process's descendants, less inductor's compile workers: torch starts that pool at a first parallel
    compile (on a machine of many cores) and keeps it for the life of the process, whichever test compiled first."""
    kids = set()
    for p in psutil.Process().children(recursive=True):
        try:
            if not any("torch/_inductor/compile_worker" in a for a in p.cmdline()):
                kids.add(p.pid)
        except psutil.Error:  # gone meanwhile
            pass
    return kids


def _held_by_other_workers(names: set[str]) -> set[str]:
    """Of ``names`` (/dev/shm entries), those that a process of another pytest-xdist worker's tree maps: a test
    running there holds them, they are not this test's. Without xdist there is no other worker: none."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        return set()
    me = psutil.Process()
    parent = me.parent()
    if parent is None:
        return set()
    others: set[int] = set()
    for worker in parent.children():
        if worker.pid != me.pid:
            others |= {worker.pid, *(p.pid for p in worker.children(recursive=True))}
    return shm_held_by(others, names)


_GROUPS_LOST: list[str] = []  # grouped tests whose group pytest-xdist could not mark (see below)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests of one ``xdist_group`` (the DDS tests) must run in one worker, one at a time; pytest-xdist marks them by
    a suffix of their node ids, which some pytest versions silently ignore: then they would run side by side."""
    if config.getoption("loadgroup", default=False):  # a pytest-xdist worker under --dist loadgroup
        _GROUPS_LOST[:] = [i.nodeid for i in items if i.get_closest_marker("xdist_group") and "@" not in i.nodeid]


@pytest.fixture(autouse=True)
def grouped_as_marked(request):
    if _GROUPS_LOST and request.node.get_closest_marker("xdist_group"):
        pytest.fail(
            f"--dist loadgroup has no effect with pytest {pytest.__version__} and this pytest-xdist: the "
            f"{len(_GROUPS_LOST)} tests of an xdist_group would run in several workers at once; install the dev "
            "extras' pytest",
            pytrace=False,
        )


@pytest.fixture(scope="session", autouse=True)
def one_intra_op_thread():
    """In a pytest-xdist worker on the CPU: one PyTorch intra-op thread in this process, as in an engine's workers
    (cpu_threads: 1) and as the first thread-mode engine leaves it anyway. Workers of two threads each would
    oversubscribe the CI machine's two cores (an idle OpenMP thread spins before it sleeps). Tests that need their
    own count set it."""
    if "PYTEST_XDIST_WORKER" in os.environ and DEVICE == "cpu":
        import torch

        torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def no_leaks():
    shm_before = set(os.listdir("/dev/shm"))
    kids_before = _children()
    sigint_before = signal.getsignal(signal.SIGINT)
    yield
    # a handler left behind swallows the next test's Ctrl-C (or a user's, where the engine is a library)
    assert signal.getsignal(signal.SIGINT) is sigint_before, f"SIGINT handler left: {signal.getsignal(signal.SIGINT)}"
    deadline = time.monotonic() + 10
    while (left := _children() - kids_before) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = [p for p in left if psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE]
    assert not alive, f"child processes left alive: {[psutil.Process(p).cmdline() for p in alive]}"
    # /dev/shm is the machine's, and tests run in parallel (pytest-xdist): an entry counts as left behind when it
    # outlives the test by the same grace the processes get, not when another test happens to hold one right now
    while new_shm := set(os.listdir("/dev/shm")) - shm_before:
        new_shm -= _held_by_other_workers(new_shm)  # a test running in another worker holds them: not this one's
        if not new_shm or time.monotonic() >= deadline:
            break
        time.sleep(0.1)
    assert not new_shm, f"/dev/shm entries left behind: {sorted(new_shm)}"


@pytest.fixture
def restart_backoff(monkeypatch):
    """``restart_backoff(seconds)``: the first restart delay for this test, in place of the supervisor's
    ``RESTART_BACKOFF_S``. The supervisor runs in the engine's own process, so this holds in process mode too."""
    from vpengine.runtime import supervisor

    def set_delay(seconds: float) -> None:
        monkeypatch.setattr(supervisor, "RESTART_BACKOFF_S", seconds)

    return set_delay


@pytest.fixture
def cli(capsys, monkeypatch):
    """``cli(*args, cwd=ROOT)``: ``vpengine ARGS`` through the CLI's own main function in this process, answered as
    a finished subprocess (exit code, stdout, stderr). The console script calls the same function; what this skips is
    a new interpreter and its torch import (seconds each), so the end-to-end tests keep the console script for the
    runs and take this for the messages and the runs whose process is not what they test."""
    from vpengine.cli.main import main

    def call(*args: str, cwd=ROOT) -> subprocess.CompletedProcess:
        monkeypatch.chdir(cwd)
        capsys.readouterr()
        code = main(list(args))
        out, err = capsys.readouterr()
        return subprocess.CompletedProcess(["vpengine", *args], code, out, err)

    return call
