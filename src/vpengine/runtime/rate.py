"""The rate gate: which frames a model runs, decided on the frames' own clock (their capture timestamps).

A model's rate limit runs on its source's timeline, not the wall clock of the machine that processes it: a live
camera's frames are stamped as they are captured, so the two agree, and a file's frames carry their position in the
recording, so a 10 fps video run faster than real time (``vpengine run``'s lockstep pacing) still gives a 5 Hz head
every second frame. The worker offers the gate every frame it takes; the gate admits it or not, and a frame it does
not admit is counted skipped at once (so a caller waiting for that frame learns it will get no output from this
model instead of waiting for one).

The gate keeps a schedule of allowed times, not a minimum spacing: each admitted frame advances the next allowed
time by one period from the *previous allowed time* (not from the frame's own time), so frames that land a little
late do not push the schedule back and N seconds of frames at R Hz give R*N +-1 runs. A frame is admitted from half a
frame interval before its allowed time (the frame nearest the schedule wins, so jitter in the stamps cannot make a
limit equal to the input rate drop frames).

The schedule starts at the first frame after start-up, a resume or a change from "unlimited". A frame that comes
after a gap in the input longer than a period (the camera paused) restarts the schedule there, with no burst of
catch-up runs; a model that fell behind because it was busy (it missed frames) catches up, up to
``MAX_DEBT_PERIODS`` runs, so a loaded machine does not silently lose runs.

Stamps are only trusted while they advance. A frame whose stamp does not move past the previous one's (a driver that
stamps every frame 0, a file played again from its start) moves the gate's clock on by the time between the two
frames' arrivals instead, so bad stamps fall back to the wall clock rather than stop a rate-limited model for good.
"""

from __future__ import annotations

import math

#: How many periods behind a busy (not starved) model may catch up before the schedule restarts.
MAX_DEBT_PERIODS = 4


class RateGate:
    def __init__(self) -> None:
        self.hz: float | None = None
        self.next_allowed = -math.inf  # on the gate's clock: from when the next frame may run
        self.last_start = -math.inf  # the gate's clock at the last admitted frame
        self.clock = -math.inf  # the gate's clock at the last frame offered: its stamps, while they advance
        self.interval = 0.0  # moving average of the spacing of the frames offered (0: not known yet)
        self._stamp = -math.inf  # stamp and arrival time of the last frame offered
        self._arrival = 0.0
        self._changed = False  # the rate changed since the last admitted frame: no debt carries over

    def update(self, hz: float | None) -> None:
        """Apply the current target rate (None: unlimited, 0: paused). A change takes effect at once."""
        if hz == self.hz:
            return
        old = self.hz
        self.hz = hz
        if hz is None or hz == 0 or old in (None, 0) or self.last_start == -math.inf:
            self.next_allowed = -math.inf  # (re)start: the schedule begins at the next frame
        else:
            self.next_allowed = self.last_start + 1.0 / hz
        self._changed = True

    @property
    def paused(self) -> bool:
        return self.hz == 0

    def admit(self, stamp: float, arrival: float, missed: int = 0) -> bool:
        """Whether the frame stamped ``stamp`` (its capture time, seconds) runs; an admitted frame schedules the next
        allowed time. ``arrival``: when it reached the engine (monotonic seconds), the clock used while stamps do not
        advance; ``missed``: frames published since the previous one offered that this model never saw (it was
        busy)."""
        prev = self.clock
        if prev == -math.inf:
            t = stamp
        elif stamp > self._stamp:
            t = prev + (stamp - self._stamp)
        else:  # the stamps stalled or went back: move on by the arrival clock
            t = prev + max(arrival - self._arrival, 0.0)
        self.clock, self._stamp, self._arrival = t, stamp, arrival
        gap = False
        if prev > -math.inf:
            gap = not missed and self.hz is not None and self.hz > 0 and t - prev > 1.0 / self.hz
            step = (t - prev) / (1 + missed)
            if not gap and step > 0:  # a pause in the input says nothing about its frame spacing
                self.interval = step if self.interval <= 0 else self.interval + 0.125 * (step - self.interval)
        if self.hz == 0:
            return False
        if self.hz is None:
            self.last_start = t
            return True
        period = 1.0 / self.hz
        slack = min(self.interval, period) / 2
        if t < self.next_allowed - slack:
            return False
        lag = t - self.next_allowed
        if (
            self.next_allowed == -math.inf
            or (gap and lag > period)
            or (self._changed and lag > 0)
            or lag > MAX_DEBT_PERIODS * period
        ):
            # first run, after an idle spell or a rate change (the old rate owes the new one nothing): start here
            self.next_allowed = t + period
        else:  # on time, a little late or early, or busy: keep the schedule (no drift)
            self.next_allowed += period
        self._changed = False
        self.last_start = t
        return True
