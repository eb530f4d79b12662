"""The leak check (tests/conftest.py) tells an entry another process maps from one nobody holds."""

from __future__ import annotations

import os
import subprocess
import sys
import uuid

from helpers.leaks import shm_held_by

HOLDER = """
import multiprocessing, sys
from multiprocessing import shared_memory
lock = multiprocessing.get_context("spawn").Lock()  # a named semaphore: sem.mp-*
seg = shared_memory.SharedMemory(create=True, size=4096)
print(lock._semlock.name.lstrip("/"), seg.name.lstrip("/"), flush=True)
sys.stdin.read()
seg.close()
seg.unlink()
"""


def test_a_semaphore_and_a_segment_another_process_maps_are_its_and_a_bare_file_is_nobodys():
    holder = subprocess.Popen([sys.executable, "-c", HOLDER], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    bare = f"vpengine-leak-probe-{uuid.uuid4().hex}"
    try:
        sem, seg = holder.stdout.readline().split()
        sem = "sem." + sem
        open(f"/dev/shm/{bare}", "wb").close()
        names = {sem, seg, bare}
        assert names <= set(os.listdir("/dev/shm"))
        assert shm_held_by([holder.pid], names) == {sem, seg}  # the semaphore too, though mapped under a temp name
        assert shm_held_by([os.getpid()], names) == set()  # this process maps none of them
    finally:
        holder.communicate("", timeout=30)
        os.unlink(f"/dev/shm/{bare}")
    assert shm_held_by([holder.pid], {sem, seg}) == {sem, seg}  # gone meanwhile: nobody's leak
