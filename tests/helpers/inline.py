"""Note [Inline launch] on the CPU: the offer is used only by slot-bound CUDA workers, so tests that exercise it on
the CPU (thread mode: the patch reaches the workers, which run in this process) turn it on for every worker."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from unittest import mock


@contextlib.contextmanager
def inline_launch(on: bool = True) -> Iterator[None]:
    with mock.patch("vpengine.runtime.prepare.inline_wanted", lambda cuda, bound: on):
        yield
