"""Note [Borrowing stderr] (io/stderr.py): what C code writes to descriptor 2 is caught for a moment and handed back,
the real stderr comes back after, borrowers in several threads do not trip over each other, and a process without a
stderr runs the block as it is."""

from __future__ import annotations

import os
import threading

from vpengine.io.stderr import captured_stderr


def test_what_is_written_to_descriptor_2_comes_back_and_stderr_is_restored_after(capfd):
    capfd.readouterr()
    with captured_stderr() as said:
        os.write(2, b"[ WARN:0] chatter\n\n  \nmore\n")
    os.write(2, b"after\n")
    assert said == ["[ WARN:0] chatter", "more"]  # blank lines dropped
    assert capfd.readouterr().err == "after\n"


def test_an_error_in_the_block_still_restores_stderr(capfd):
    capfd.readouterr()
    try:
        with captured_stderr():
            raise KeyError("x")
    except KeyError:
        pass
    os.write(2, b"after\n")
    assert capfd.readouterr().err == "after\n"


def test_without_a_descriptor_2_the_block_runs_as_it_is(monkeypatch):
    def no_stderr(fd: int) -> int:
        raise OSError(9, "Bad file descriptor")

    monkeypatch.setattr(os, "dup", no_stderr)
    ran = []
    with captured_stderr() as said:
        ran.append(True)
    assert ran == [True] and said == []


def test_borrowers_in_several_threads_each_get_their_own_lines_and_leave_stderr_as_it_was(capfd):
    before = os.fstat(2)
    got: dict[int, list[list[str]]] = {i: [] for i in range(4)}

    def borrow(i: int) -> None:
        for _ in range(25):
            with captured_stderr() as said:
                os.write(2, f"thread {i}\n".encode())
            got[i].append(said)

    threads = [threading.Thread(target=borrow, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    after = os.fstat(2)
    assert (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino)
    assert all(said == [f"thread {i}"] for i, lists in got.items() for said in lists) and all(
        len(lists) == 25 for lists in got.values()
    )
