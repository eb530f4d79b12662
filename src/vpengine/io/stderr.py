"""The process's stderr borrowed for a moment: :func:`captured_stderr`.

Note [Borrowing stderr]
~~~~~~~~~~~~~~~~~~~~~~~
OpenCV's backends and FFmpeg's and GStreamer's C code write straight to file descriptor 2, below Python's
``sys.stderr``: a WARN line for each backend OpenCV tries and fails with, FFmpeg's errors, an encoder that is not
there. Around a one-line refusal they read as a crash. Neither OpenCV's log level nor Python's logging reaches them,
so the only way to keep them off the terminal is to point descriptor 2 elsewhere while the C code runs.

The cost: descriptor 2 is the whole process's. While it is borrowed, whatever ANY thread writes to stderr goes to
the borrower's file too: a warning, a log line, a progress bar from another thread. The lines come back to the
borrower, who logs them at DEBUG (``vpengine -vv`` shows them), so nothing is lost, but it is late and quiet. So
borrow it for as short a time as possible (one open, one probe), never around a frame loop, and prefer doing a
noisy thing once per process (a cached probe) to doing it per file.

Two threads borrowing at once would each save the other's file as "the real stderr" and one would leave descriptor 2
pointing at a deleted file for good; a lock serialises borrowers (re-entrant, so a borrower may nest).
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import threading
from collections.abc import Iterator

_lock = threading.RLock()


@contextlib.contextmanager
def captured_stderr() -> Iterator[list[str]]:
    """Descriptor 2 goes to a temporary file for the block (Note [Borrowing stderr]); the non-blank lines written to it
    meanwhile come back in the yielded list, filled when the block ends. Where there is no stderr to borrow (closed
    descriptor 2, no temporary file) the block runs as it is and the list stays empty."""
    said: list[str] = []
    with _lock, contextlib.ExitStack() as stack:
        with contextlib.suppress(Exception):  # a closed or replaced sys.stderr has nothing to flush
            sys.stderr.flush()
        saved, tmp = -1, None
        try:
            saved = os.dup(2)
            stack.callback(os.close, saved)
            tmp = stack.enter_context(tempfile.TemporaryFile())
        except OSError:  # no descriptor 2 (a daemon started with it closed), or no temporary file: nothing to guard
            pass
        if tmp is None:
            yield said
            return
        os.dup2(tmp.fileno(), 2)
        try:
            yield said
        finally:
            with contextlib.suppress(Exception):
                sys.stderr.flush()
            os.dup2(saved, 2)
            tmp.seek(0)
            said.extend(line for line in tmp.read().decode(errors="replace").splitlines() if line.strip())
