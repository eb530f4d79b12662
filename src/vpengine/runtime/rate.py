"""The rate gate: a schedule of allowed start times, not a sleep after the fact.

Each run advances the next allowed start by one period from the *previous allowed start* (not from when the run
happened), so late runs do not push the schedule back and N seconds at R Hz give R*N +-1 runs. After an idle spell
the schedule is not allowed to lag by more than half a period, so there is no burst of catch-up runs either.
"""

from __future__ import annotations

import math


class RateGate:
    def __init__(self) -> None:
        self.hz: float | None = None
        self.next_allowed = -math.inf
        self.last_start = -math.inf

    def update(self, hz: float | None, now: float) -> None:
        """Apply the current target rate (None: unlimited, 0: paused). A change takes effect at once."""
        if hz == self.hz:
            return
        old = self.hz
        self.hz = hz
        if hz is None or hz == 0:
            self.next_allowed = -math.inf
        elif old == 0 or self.last_start == -math.inf:
            self.next_allowed = now  # resume: run as soon as there is data
        else:
            self.next_allowed = self.last_start + 1.0 / hz

    @property
    def paused(self) -> bool:
        return self.hz == 0

    def wait_time(self, now: float) -> float:
        """Seconds until a run may start (0: now; inf: paused)."""
        if self.hz == 0:
            return math.inf
        return max(0.0, self.next_allowed - now)

    def started(self, t: float) -> None:
        """Record a run starting at ``t`` and schedule the next allowed start."""
        self.last_start = t
        if self.hz:
            period = 1.0 / self.hz
            self.next_allowed = max(self.next_allowed + period, t - 0.5 * period)
