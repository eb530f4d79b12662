"""The rate gate: a schedule of allowed start times, not a sleep after the fact.

Each run advances the next allowed start by one period from the *previous allowed start* (not from when the run
happened), so runs that start late do not push the schedule back and N seconds at R Hz give R*N +-1 runs.

The schedule starts at the first run after start-up, a resume or a rate change from "unlimited" -- not when the
worker begins to wait -- so a model that waited for its first frame does not get an early second run. Later, a run
whose input arrived more than a whole period after the gate opened means the model was idle (the camera paused):
the schedule restarts from that run, with no burst of catch-up runs. Shorter waits keep the schedule (no drift when
the limit equals the input rate), and a model that was late because the CPU was busy catches up, up to
``MAX_DEBT_PERIODS`` runs, so a loaded machine does not silently lose runs.
"""

from __future__ import annotations

import math

#: How many periods behind a busy (not starved) model may catch up before the schedule restarts.
MAX_DEBT_PERIODS = 4


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
        if hz is None or hz == 0 or old in (None, 0) or self.last_start == -math.inf:
            self.next_allowed = -math.inf  # (re)start: the schedule begins at the next run
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

    def started(self, t: float, starved: bool = False) -> None:
        """Record a run starting at ``t`` and schedule the next allowed start.

        ``starved``: the input for this run arrived after the gate had opened.
        """
        self.last_start = t
        if self.hz:
            period = 1.0 / self.hz
            lag = t - self.next_allowed
            if (
                self.next_allowed == -math.inf
                or (starved and lag > period)
                or lag > MAX_DEBT_PERIODS * period
            ):
                self.next_allowed = t + period  # first run, or after an idle spell: the schedule starts here
            else:
                self.next_allowed += period  # on time, a little late, or busy: keep the schedule (no drift)
