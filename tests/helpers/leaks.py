"""Who holds a /dev/shm entry: the leak check's way to tell a test's own entries from another worker's."""

from __future__ import annotations

import os
from collections.abc import Iterable


def shm_held_by(pids: Iterable[int], names: set[str]) -> set[str]:
    """Of ``names`` (/dev/shm entries), those that one of ``pids`` maps, and those gone meanwhile.

    Matched by inode, not name: glibc creates a named semaphore (multiprocessing's ``sem.mp-*``) under a temporary
    name, maps it and only then links it to its own, so a process's maps show the temporary name, deleted."""
    mapped: set[int] = set()
    for pid in pids:
        try:
            with open(f"/proc/{pid}/maps") as f:
                mapped |= {int(line.split()[4]) for line in f if "/dev/shm/" in line}
        except OSError:  # it ended meanwhile
            continue
    held = set()
    for name in names:
        try:
            if os.stat(f"/dev/shm/{name}").st_ino in mapped:
                held.add(name)
        except OSError:  # gone meanwhile: not left behind either
            held.add(name)
    return held
