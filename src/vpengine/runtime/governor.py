"""The governor: when the device cannot serve every lane, the engine decides who gives way.

Note [Give way]
~~~~~~~~~~~~~~~
Every lane (a (model, camera) pair, Note [Cameras] in worker.py) has a priority key, its head's priority then its
camera's, higher more important (runtime/priority.py). A lane *claims* the rate it wants now: its target rate, or the
rate its camera's frames come at if that is lower or it has none; its deadline is one period of its target (an output
later than that after its frame's submit is counted in ``deadline_misses``). When the device is over-subscribed every
worker slows down alike; the governor, a thread in the engine's process that wakes every ``TICK_S`` while priorities
differ (with all equal it sleeps until ``set_priority`` wakes it), watches each lane's achieved rate and end-to-end
latency in the control block and, when a lane misses its claim (achieved below it by more than ``TOLERANCE``, or its
p99 latency past its deadline), lowers a *throttle cap* on the least important lanes, which their workers obey like a
rate limit (``ControlBlock.rate`` is the lower of target and cap; the frames the cap holds back are skipped, counted
with reason ``priority``, never queued). So the load that lanes of lower priority put on the device drops until the
lane that missed holds again.

The caps form a water level over the distinct priority keys, lowest first (``Policy``): the ``k`` lowest groups of
lanes run at the floor (``FLOOR_HZ``: throttled lanes still show signs of life), group ``k`` at a share ``f`` of
its claim, every group above it uncapped. A miss cuts ``f`` (multiplicative decrease, from the group's achieved
share if that is lower, by ``DECREASE`` or deeper the further the lane that missed fell short) and, once the group is
at the floor, moves on to the next group, but never to the group of the lane that missed or above it: lanes of equal
priority never throttle each other, and the most important lanes are never capped. Each change is judged on
evidence gathered after it (``SETTLE_S`` at least), so one cut's effect is seen before the next; from full rate to
the floor takes a few cuts, about a second. When every uncapped lane has held its claim with margin (rate within
``TOLERANCE / 2``, p99 latency within ``LATENCY_MARGIN`` of its deadline) for ``HOLD_S``, the governor probes: ``f``
doubles (at least ``STEP``) and the caps come off group by group, so a load that fell is given back within seconds.
A miss within ``PROBE_S`` of a probe undoes it (back to where it was, not a cut) and doubles the wait before the
next probe (up to ``MAX_HOLD_S``; a probe that holds resets it): under a load that stays, the caps do not oscillate,
they are tried now and then. A change of priorities moves the caps with the ranks at once (a lane raised above the
level is uncapped at the next tick; ``set_priority`` wakes the governor for it): the load stays what it was, only
who carries it changes.

The foundation model serves every camera: its lane of a camera is capped only when every head lane of that camera
is, at the highest of their caps, so it never runs below what its most important consumer needs. Nothing is capped
while all priorities are equal (the default), so an engine without priorities behaves as before.
A lane that misses because its own work is too slow for its claim takes every lower lane down to the floor to no
avail: the floor bounds that cost. Inside one batch of a model the same key decides: while the model cannot keep up,
Note [Cameras]'s deferral leaves the least important lane's frame for the next batch (among equals, the camera last
in the configured order), so a lane raised at run time is not the one that waits a batch.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from vpengine import checks
from vpengine.config import EngineConfig
from vpengine.runtime.control import ControlBlock
from vpengine.runtime.lanes import Lane, Lanes
from vpengine.runtime.priority import priority_key, stream_levels

log = logging.getLogger("vpengine.governor")

TICK_S = 0.1  # how often the governor looks
WINDOW_S = 1.0  # the longest stretch of the past a decision rests on
SETTLE_S = 0.3  # evidence after a change before the next cut
HOLD_S = 0.6  # evidence of margin after a change before caps are raised (a probe)
MAX_HOLD_S = 4.0  # the longest wait before a probe, after probes that failed
PROBE_S = 1.0  # a miss this soon after a probe is the probe's
TOLERANCE = 0.1  # achieved below (1 - TOLERANCE) x its claim: a miss
LATENCY_MARGIN = 0.8  # p99 latency within this share of the deadline: held with margin
DECREASE = 0.5
STEP = 0.1
FLOOR_HZ = 0.5
MIN_RUNS = 3  # a lane is judged once the evidence should hold this many of its runs

Key = tuple[int, int]


@dataclass(frozen=True)
class LaneView:
    """One lane as the governor sees it at a tick, over the evidence since the last change."""

    entry: str
    key: Key
    claim_hz: float  # the rate it wants now (0: none: paused, no frames, not serving)
    achieved_hz: float
    p99_s: float  # end-to-end latency; NaN: no outputs
    deadline_s: float  # NaN: none (no target rate)
    span_s: float  # how long the evidence is

    def verdict(self) -> str | None:
        """``miss``, ``margin`` (held with margin), ``held``, or None (no claim, or too little evidence yet)."""
        if self.claim_hz <= 0 or self.span_s * self.claim_hz < MIN_RUNS:
            return None
        if self.p99_s > self.deadline_s or self.achieved_hz < (1 - TOLERANCE) * self.claim_hz:  # NaN: False
            return "miss"
        if (
            self.achieved_hz >= (1 - TOLERANCE / 2) * self.claim_hz
            and not self.p99_s > LATENCY_MARGIN * self.deadline_s
        ):
            return "margin"
        return "held"


class Policy:
    """The decisions of Note [Give way] on snapshots: no threads and no clock of its own, so tests drive it."""

    def __init__(self, floor_hz: float = FLOOR_HZ) -> None:
        self.floor_hz = floor_hz
        self.k = 0  # groups below k run at the floor, group k at f of its claim, those above uncapped
        self.f = 1.0
        self.changed_at = -math.inf
        self.hold_s = HOLD_S  # the wait before the next probe
        self._probe: tuple[float, int, float] | None = None  # the last probe: when, and the (k, f) before it
        self._ranks: tuple[tuple[str, Key], ...] = ()

    @property
    def throttling(self) -> bool:
        return self.k > 0 or self.f < 1

    def evidence_since(self, now: float) -> float:
        """From when the next decision's evidence counts: after the last change, within WINDOW_S."""
        return max(now - WINDOW_S, self.changed_at)

    def decide(self, lanes: Sequence[LaneView], now: float) -> dict[str, float | None]:
        """Every lane's cap (None: none) after looking at ``lanes`` at time ``now``."""
        ranks = tuple((v.entry, v.key) for v in lanes)
        if ranks != self._ranks:  # priorities changed: the caps move with the ranks; judge them afresh
            self._ranks, self.changed_at, self._probe = ranks, now, None
        groups = sorted({v.key for v in lanes})
        rank = {key: i for i, key in enumerate(groups)}
        if len(groups) < 2:
            self.k, self.f = 0, 1.0
        else:
            if self.k > len(groups) - 2:
                self.k = len(groups) - 2
            self._adjust(lanes, rank, now)
        caps: dict[str, float | None] = {}
        for v in lanes:
            share = self._share(rank[v.key])
            caps[v.entry] = None if share >= 1 else max(self.floor_hz, share * v.claim_hz)
        return caps

    def _share(self, group: int) -> float:
        return 0.0 if group < self.k else self.f if group == self.k else 1.0

    def _adjust(self, lanes: Sequence[LaneView], rank: dict[Key, int], now: float) -> None:
        verdicts = [(v, v.verdict()) for v in lanes if self._share(rank[v.key]) >= 1]  # the uncapped lanes'
        missed = [v for v, verdict in verdicts if verdict == "miss"]
        since = now - self.changed_at
        if missed and since >= SETTLE_S:
            probe, self._probe = self._probe, None
            if probe is not None and now - probe[0] <= PROBE_S:  # the probe was too much: undo it, wait longer
                self.k, self.f = probe[1], probe[2]
                self.hold_s = min(2 * self.hold_s, MAX_HOLD_S)
                self.changed_at = now
                return
            short = min(v.achieved_hz / v.claim_hz for v in missed) / (1 - TOLERANCE)  # 1: a latency miss
            cut = DECREASE * max(0.25, min(1.0, short))
            self._decrease(lanes, rank, max(rank[v.key] for v in missed), cut, now)
        elif not missed and self.throttling and since >= self.hold_s and all(v != "held" for _, v in verdicts):
            if self._probe is not None:
                self.hold_s = HOLD_S  # the last probe held
            self._probe = (now, self.k, self.f)
            self._increase(now)

    def _decrease(self, lanes: Sequence[LaneView], rank: dict[Key, int], missing: int, cut: float, now: float) -> None:
        """Cut the lowest group that can still give, if it is below group ``missing``, to ``cut`` of its share."""
        k, f = self.k, self.f
        while True:
            if f <= 0:  # at the floor: the next group gives way
                k, f = k + 1, 1.0
            if k >= missing:
                return  # nothing below the lane that missed is left to give
            group = [v for v in lanes if rank[v.key] == k and v.claim_hz > 0]
            top = max((v.claim_hz for v in group), default=0.0)
            if f * top > self.floor_hz:
                break
            f = 0.0
        achieved = max(min(1.0, v.achieved_hz / v.claim_hz) for v in group)
        f = cut * min(f, achieved)
        self.k, self.f = k, (0.0 if f * top <= self.floor_hz else f)
        self.changed_at = now

    def _increase(self, now: float) -> None:
        self.f = max(2 * self.f, self.f + STEP)
        if self.f >= 1:
            self.k, self.f = (self.k - 1, 0.0) if self.k > 0 else (0, 1.0)
        self.changed_at = now


def achieved_rate(starts: np.ndarray, now: float, span_s: float) -> float:
    """Runs per second from sorted run start times: their pace while they keep coming, else their count over the
    span (a lane that stopped has no pace)."""
    n = len(starts)
    if n >= 2 and starts[-1] > starts[0]:
        pace = (n - 1) / (starts[-1] - starts[0])
        if now - starts[-1] <= 2.0 / pace:
            return float(pace)
    return n / span_s if span_s > 0 else 0.0


class Governor:
    """The thread around a ``Policy``: reads the control block, decides, writes the caps (Note [Give way]). Also the
    one writer of priorities in the control block: from the config at construction, then ``set_priority``."""

    def __init__(
        self,
        control: ControlBlock,
        cfg: EngineConfig,
        lanes: Lanes,
        clock: Callable[[], float] = time.monotonic,
        tick_s: float = TICK_S,
    ) -> None:
        self.control = control
        self.lanes = lanes
        # the lanes priorities apply to: every head's, and the foundation model's entry for each camera
        self._heads = _head_lanes(lanes)
        self._seated: Lanes | None = None  # the lanes of a head being added (``seat``), until ``relane``
        self._foundation = {lane.camera: lane.entry for lane in lanes.of("foundation")}
        self.policy = Policy()
        self._clock = clock
        self._tick = tick_s
        self._offered: dict[str, deque[tuple[float, int]]] = {c: deque() for c in self._foundation}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._failed = False
        for lane in self._heads:
            control.set(lane.entry, "priority", cfg.head(lane.model).priority)
        for cam in cfg.cameras:
            for entry in self._camera_entries(cam.name):
                control.set(entry, "camera_priority", cam.priority)
        self._refresh_foundation()

    def seat(self, cfg: EngineConfig, lanes: Lanes) -> None:
        """Before an added head's worker starts (Note [Heads at run time] in lanes.py): its lanes in ``lanes`` take
        its configured priority and their cameras', and every model of ``lanes`` its stream level, so the worker
        starts on the stream it keeps; the lanes governed stay the old ones until ``relane``, and priority changes
        meanwhile count the seated head in the levels. After a failed add, ``unseat`` puts the levels back."""
        with self._lock:
            # a camera's priority as it is now (set_priority may have changed it): its foundation lane shows it
            cameras = {cam: int(self.control.get(e, "camera_priority")) for cam, e in self._foundation.items()}
            for lane in _head_lanes(lanes):
                if lane not in self._heads:
                    self.control.set(lane.entry, "priority", cfg.head(lane.model).priority)
                    self.control.set(lane.entry, "camera_priority", cameras.get(lane.camera, 0))
            self._seated = lanes
            self._write_levels(lanes)

    def unseat(self) -> None:
        """An add that ``seat`` began failed: the levels of the lanes governed, as before it."""
        with self._lock:
            self._seated = None
            self._write_levels(self.lanes)

    def relane(self, cfg: EngineConfig, lanes: Lanes) -> None:
        """A head was added or removed (Note [Heads at run time] in lanes.py): the lanes to govern are ``lanes``;
        an added head's lanes start with its configured priority and their cameras' (``seat``)."""
        self.seat(cfg, lanes)
        with self._lock:
            self.lanes, self._heads, self._seated = lanes, _head_lanes(lanes), None
            self._refresh_foundation()
        self.wake()

    # ------------------------------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="vpengine-governor", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stopping = True
        self._wake.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self._thread = None

    def wake(self) -> None:
        """Decide now rather than at the next tick."""
        self._wake.set()

    def _run(self) -> None:
        idle = False
        while True:
            # Nothing is capped while every lane has the same priority (Note [Give way]): then the governor sleeps
            # until set_priority wakes it, and starts its measurements afresh.
            self._wake.wait(None if idle else self._tick)
            self._wake.clear()
            if self._stopping:
                return
            try:
                was_idle, idle = idle, not self.ranked()
                if idle:
                    continue
                if was_idle:
                    for hist in self._offered.values():
                        hist.clear()
                self.step()
            except Exception:  # a bug here must not take the engine down; said once, then quietly retried
                if not self._failed:
                    log.exception("the governor failed to decide; caps stay as they are")
                self._failed = True

    # ---------------------------------------------------------------------------------------------- steps
    def ranked(self) -> bool:
        """Whether the lanes' priorities differ, so that some may give way to others; else none is capped."""
        with self._lock:
            keys = {priority_key(self.control, e) for e in self._entries()}
            return len(keys) > 1 or self.policy.throttling

    def _entries(self) -> list[str]:
        return [lane.entry for lane in self._heads]

    def step(self, now: float | None = None) -> dict[str, float | None]:
        """One decision: measure, decide, write the caps; returns the head lanes' caps."""
        now = self._clock() if now is None else now
        with self._lock:  # not while relane renames the lanes
            caps = self.policy.decide(self.views(now), now)
            self._apply(caps)
        return caps

    def views(self, now: float) -> list[LaneView]:
        ctl = self.control
        since = self.policy.evidence_since(now)
        span = now - since
        inputs = self._input_rates(now)
        views = []
        for lane in self._heads:
            target = ctl.target(lane.entry)
            upstream = inputs[lane.camera]
            f_target = ctl.target(self._foundation[lane.camera])
            if f_target is not None:
                upstream = min(upstream, f_target)
            claim = upstream if target is None else min(target, upstream)
            if ctl.state(lane.model) not in ("running", "ready", "paused"):
                claim = 0.0  # loading, restarting, failed, hung: it can hold nothing now
            starts, e2e = ctl.recent_runs(lane.entry, since)
            views.append(
                LaneView(
                    entry=lane.entry,
                    key=priority_key(ctl, lane.entry),
                    claim_hz=claim,
                    achieved_hz=achieved_rate(starts, now, span),
                    p99_s=float(np.percentile(e2e, 99)) if len(e2e) else math.nan,
                    deadline_s=1.0 / target if target else math.nan,
                    span_s=span,
                )
            )
        return views

    def _input_rates(self, now: float) -> dict[str, float]:
        """Each camera's frame rate over the last WINDOW_S: every frame submitted is one the foundation model ran,
        skipped or dropped."""
        rates = {}
        for cam, entry in self._foundation.items():
            offered = sum(self.control.get(entry, f) for f in ("runs", "skipped", "dropped"))
            hist = self._offered[cam]
            hist.append((now, offered))
            while len(hist) > 2 and hist[1][0] <= now - WINDOW_S:
                hist.popleft()
            (t0, n0), (t1, n1) = hist[0], hist[-1]
            rates[cam] = (n1 - n0) / (t1 - t0) if t1 - t0 >= 2 * TICK_S else 0.0
        return rates

    def _apply(self, caps: dict[str, float | None]) -> None:
        for lane in self._heads:
            self._write(lane.entry, caps[lane.entry])
        for cam, entry in self._foundation.items():
            mine = [caps[lane.entry] for lane in self._heads if lane.camera == cam]
            self._write(entry, None if not mine or None in mine else max(c for c in mine if c is not None))

    def _write(self, entry: str, hz: float | None) -> None:
        """Set a cap that moved by more than 5%: a cap follows its claim's measured rate, and every change restarts
        the lane's rate schedule (rate.py), so jitter in the measurement is not passed on."""
        old = self.control.cap(entry)
        if (hz is None) != (old is None) or (hz is not None and old is not None and abs(hz - old) > 0.05 * old):
            self.control.set_cap(entry, hz)

    # ------------------------------------------------------------------------------------------- priorities
    def set_priority(self, head: str | None, priority: object, camera: str | None = None) -> None:
        """``Engine.set_priority``: validate everything first (nothing changes on an error), then write and wake."""
        value = checks.priority(priority)
        if head is None:
            if camera not in self.lanes.cameras:
                raise ValueError(
                    f"a camera's priority (no head named) needs one of the cameras {list(self.lanes.cameras)}, "
                    f"got {camera!r}"
                )
            entries, field = self._camera_entries(camera), "camera_priority"
        elif head == "foundation":
            raise KeyError(f"the foundation model's priority follows its heads'; heads: {self._head_names()}")
        elif head not in self._head_names():
            raise KeyError(f"no head named {head!r}; heads: {self._head_names()}")
        else:
            entries, field = [lane.entry for lane in self.lanes.select(head, camera)], "priority"
        with self._lock:
            for entry in entries:
                self.control.set(entry, field, value)
            self._refresh_foundation()
        self.wake()

    def _head_names(self) -> list[str]:
        return [m for m in self.lanes.by_model if m != "foundation"]

    def _camera_entries(self, camera: str) -> list[str]:
        return [lane.entry for lane in self._heads if lane.camera == camera] + [self._foundation[camera]]

    def _refresh_foundation(self) -> None:
        """The foundation model's lane of a camera shows the priority of its most important head lane there (the
        lowest of all where no head serves that camera: its frames are the first the foundation defers, Note
        [Cameras]); every lane shows its model's CUDA stream level."""
        for cam, entry in self._foundation.items():
            mine = [self.control.get(lane.entry, "priority") for lane in self._heads if lane.camera == cam]
            self.control.set(entry, "priority", max(mine, default=checks.MIN_PRIORITY))
        self._write_levels(self.lanes if self._seated is None else self._seated)

    def _write_levels(self, lanes: Lanes) -> None:
        """Each model's CUDA stream level (runtime/priority.py) into every lane of it: a head's from its most
        important lane, the foundation model's from the most important head lane of all."""
        heads = {
            m: max(int(self.control.get(lane.entry, "priority")) for lane in of)
            for m, of in lanes.by_model.items()
            if m != "foundation" and of
        }
        levels = stream_levels({**heads, "foundation": max(heads.values(), default=0)})
        for m, of in lanes.by_model.items():
            for lane in of:
                self.control.set(lane.entry, "stream_level", levels[m])


def _head_lanes(lanes: Lanes) -> tuple[Lane, ...]:
    return tuple(lane for model, of in lanes.by_model.items() if model != "foundation" for lane in of)
