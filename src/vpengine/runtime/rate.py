"""The rate gate: a schedule of allowed start times, not a sleep after the fact.

Each run advances the next allowed start by one period from the *previous allowed start* (not from when the run
happened), so runs that start late do not push the schedule back and N seconds at R Hz give R*N +-1 runs.

Lateness has two causes, told apart by the worker: the model was *starved* (no new input when the gate opened:
just started, just resumed, the camera paused) or it was *descheduled* (input was there but the CPU was busy). A
starved model was idle, so its schedule restarts from the run that ended the wait (no early second run, no burst of
catch-up runs). A descheduled model keeps its schedule and catches up, up to ``MAX_DEBT_PERIODS`` runs, so a loaded
machine does not silently lose runs.
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

    def started(self, t: float, starved: bool = False) -> None:
        """Record a run starting at ``t`` and schedule the next allowed start.

        ``starved``: the input for this run arrived after the gate had opened (the model was idle, not late).
        """
        self.last_start = t
        if self.hz:
            period = 1.0 / self.hz
            if starved:  # idle until this input came: the schedule starts afresh from this run
                self.next_allowed = max(self.next_allowed + period, t + period)
            elif t - self.next_allowed > MAX_DEBT_PERIODS * period:  # far behind: give up the debt
                self.next_allowed = t + period
            else:  # on time, or late because busy: keep the schedule (catch up)
                self.next_allowed += period
