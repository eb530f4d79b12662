"""pytest-xdist groups (``--dist loadgroup``) of tests that share what a worker process sets up once."""

from __future__ import annotations

import pytest

#: Tests that compile with inductor in the pytest process (and the process-mode twin of one of them). A process's
#: first inductor compile probes the CPU's vector ISAs by building and loading test programs (some 15 s of g++ on
#: a 2-core machine, whichever test comes first) and starts inductor's compile workers; in one worker that happens
#: once, not once a worker. The tests assert nothing about it.
INDUCTOR = pytest.mark.xdist_group("inductor")
