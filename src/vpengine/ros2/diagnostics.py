"""What /diagnostics says: a status per model, the counting and logging of rejected messages, and the input link.

The interface's own status (its counters) is put together by :meth:`vpengine.ros2.core.Ros2Core.diagnostics` from
these parts. No middleware here.
"""

from __future__ import annotations

import collections
import logging
import math
import re
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from vpengine.ros2.messages import Header

log = logging.getLogger("vpengine.ros2")

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR, STALE = 0, 1, 2, 3


@dataclass
class Status:
    """One diagnostic_msgs/DiagnosticStatus."""

    level: int
    name: str
    message: str
    hardware_id: str
    values: list[tuple[str, str]] = field(default_factory=list)


@dataclass
class DiagnosticsOut:
    """A diagnostic_msgs/DiagnosticArray to publish."""

    header: Header
    status: list[Status]


# --------------------------------------------------------------------------------------------- diagnostics
def _fmt(v: Any) -> str:
    if v is None:
        return "none"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.2f}"
    return str(v)


def model_status(name: str, m: Mapping[str, Any], prefix: str, hardware_id: str) -> Status:
    """One model's health from ``Engine.stats()["models"][name]``: OK; WARN while restarting or paused (also
    starting/loading); ERROR when failed for good or hung (thread mode, Note [Hung threads])."""
    state = str(m.get("state", "unknown"))
    target = m.get("target_hz")
    achieved = float(m.get("achieved_hz") or 0.0)
    tgt = "unlimited" if target is None else f"{target:g} Hz"
    lat = m.get("latency_ms") or {}
    paused = state == "paused" or target == 0
    if state in ("failed", "hung"):
        level, msg = ERROR, f"{state}: {m.get('last_error') or 'no error text'}"
    elif state == "restarting":
        level, msg = WARN, f"restarting after a crash ({m.get('restarts', 0)} restarts so far)"
    elif paused:
        level, msg = WARN, "paused (rate 0)"
    elif state in ("starting", "loading"):
        level, msg = WARN, f"{state}"
    else:
        level, msg = OK, f"{state}, {achieved:.1f} Hz (target {tgt}{_capped(m)})"
    values = [
        ("state", state),
        ("target_hz", "unlimited" if target is None else _fmt(float(target))),
        ("achieved_hz", _fmt(achieved)),
        ("runs", _fmt(m.get("runs", 0))),
        ("skipped", _fmt(m.get("skipped", 0))),
        ("drops", _fmt(m.get("dropped", 0))),
        ("errors", _fmt(m.get("errors", 0))),
        ("restarts", _fmt(m.get("restarts", 0))),
        ("latency_p50_ms", _fmt(lat.get("p50"))),
        ("latency_p99_ms", _fmt(lat.get("p99"))),
        *_giving_way(m),
    ]
    return Status(level, f"{prefix}: {name}", msg, hardware_id, values)


def _capped(m: Mapping[str, Any]) -> str:
    """Note [Give way] (runtime/governor.py): a model throttled for more important ones says so in its message."""
    cap = m.get("cap_hz")
    return "" if cap is None else f", capped at {cap:g} Hz for higher priorities"


def _giving_way(m: Mapping[str, Any], model: str | None = None) -> list[tuple[str, str]]:
    """A model's priority (and its camera's), its throttle cap while it has one, deadline misses and skips by reason
    (Note [Give way]), as far as ``m`` (``Engine.stats()`` of the model) has them; keys prefixed ``<model>.`` when
    given."""
    pre = "" if model is None else f"{model}."
    keys = ("priority", "camera_priority", "cap_hz", "deadline_misses")
    values = [(f"{pre}{k}", _fmt(m[k])) for k in keys if m.get(k) is not None]
    values += [(f"{pre}skipped_by.{r}", _fmt(n)) for r, n in (m.get("skipped_by") or {}).items()]
    return values


def camera_status(
    camera: str, counts: Mapping[str, int], models: Mapping[str, Mapping[str, Any]], prefix: str, hardware_id: str
) -> Status:
    """One camera's status, with several cameras: its input ``counts`` and the rates and counts of its ``models``
    (``Engine.stats()["cameras"][camera]``)."""
    values = [(k, str(counts[k])) for k in ("received", "submitted", "superseded", "rejected", "not_ready")]
    for model, m in models.items():
        target = m.get("target_hz")
        values += [
            (f"{model}.target_hz", "unlimited" if target is None else _fmt(float(target))),
            (f"{model}.achieved_hz", _fmt(float(m.get("achieved_hz") or 0.0))),
            *((f"{model}.{k}", _fmt(m.get(k, 0))) for k in ("runs", "skipped", "late", "deferred")),
            *_giving_way(m, model),
        ]
    message = f"{counts['submitted']} frames in of {counts['received']} received"
    return Status(OK, f"{prefix}: camera {camera}", message, hardware_id, values)


# ------------------------------------------------------------------------------------------------ rejections
#: Different texts of one reason logged at once within its window (a second and a third encoding), at most: past
#: them a reason's lines are one per window again, so a text that changes with every message cannot flood the log
DISTINCT_TEXTS = 3
_DIGITS = re.compile(r"\d+")


class Rejections:
    """Note [Rejection log]: bad inputs are counted and logged per reason, never one line per frame, never only once.

    The first rejection of each reason (:attr:`InputError.reason`: encoding, short_data, step, malformed ...) is
    logged at once with its full text, and so is a different text of the same reason (up to DISTINCT_TEXTS in a
    window), so a different later failure is never hidden behind the first one; after that each reason logs at most
    one line per ``every_s`` seconds, saying how many were not logged. ``recent()``
    names the reasons seen in the last ``recent_s`` seconds: the interface status in /diagnostics warns while it is
    not empty and so goes back to OK once good frames have flowed that long, instead of warning for the rest of the
    run. ``where`` starts each line (what was rejected, and by whom). Thread-safe; ``clock`` is for tests.
    """

    def __init__(
        self,
        where: str,
        logger: logging.Logger = log,
        every_s: float = 10.0,
        recent_s: float = 5.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.where = where
        self.counts: collections.Counter[str] = collections.Counter()
        self._log, self.every_s, self.recent_s, self.clock = logger, every_s, recent_s, clock
        self._last: dict[str, float] = {}  # reason -> time of its newest rejection
        self._logged: dict[str, float] = {}  # reason -> time of its newest log line
        self._unlogged: collections.Counter[str] = collections.Counter()
        self._texts: dict[str, set[str]] = {}  # reason -> the texts logged in its current window
        self._lock = threading.Lock()

    def add(self, reason: str, text: str) -> None:
        now = self.clock()
        with self._lock:
            self.counts[reason] += 1
            self._last[reason] = now
            logged = self._logged.get(reason)
            said = _DIGITS.sub("N", text)  # what it says, not which message or how many bytes
            if logged is not None and now - logged < self.every_s:  # within its window
                seen = self._texts[reason]
                if said in seen or len(seen) >= DISTINCT_TEXTS:
                    self._unlogged[reason] += 1
                    return
                seen.add(said)  # another failure of this reason (a second encoding): said at once, as a first is
                plain = True
            else:  # a new window
                plain = logged is None
                self._logged[reason] = now
                self._texts[reason] = {said}
            more = 0 if plain else self._unlogged[reason]
            self._unlogged[reason] = 0  # "not logged since the last line": from this line on
            total = self.counts[reason]
        if plain:
            self._log.warning("%s (%s): %s", self.where, reason, text)
        else:
            self._log.warning(
                "%s (%s; %d in all, %d not logged since the last line): %s",
                self.where,
                reason,
                total,
                more,
                text,
            )

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def recent(self) -> list[str]:
        """The reasons rejected within the last ``recent_s`` seconds, sorted."""
        now = self.clock()
        with self._lock:
            return sorted(r for r, t in self._last.items() if now - t < self.recent_s)


# ---------------------------------------------------------------------------------------------- input link
#: A publisher matched this long with nothing received is reported (Note [Input link]).
SILENT_AFTER_S = 5.0


def receive_buffer_limit() -> int | None:
    """The largest socket receive buffer an unprivileged process gets (Linux ``net.core.rmem_max``); None where
    unknown."""
    try:
        with open("/proc/sys/net/core/rmem_max") as f:
            return int(f.read().strip())
    except (OSError, ValueError):
        return None


def receive_buffer_advice(limit: int | None, frame_bytes: int) -> str | None:
    """Note [Input link]: what to do when the UDP receive buffer cannot hold one input frame; None when it can.

    A best-effort sample (cameras publish with the sensor-data profile) arrives as a burst of UDP datagrams; the
    ones that do not fit the socket's receive buffer while the receiving thread is busy are dropped, and a sample
    missing one fragment is lost whole, without any count on either side (DDS reports no sample lost for it). On
    loopback a 1080p frame (6.2 MB) came through 36 of 150 times with cyclonedds' default 1 MB buffer and 113 of
    150 with 3 MB; all 150 with 4 MB. So the buffer must hold a whole frame. The kernel caps what a process asks
    for at ``net.core.rmem_max`` (Linux default 208 kB).
    """
    if limit is None or limit >= frame_bytes:
        return None
    want = 1 << max(2 * frame_bytes - 1, 1).bit_length()  # two frames, rounded up to a power of two
    return (
        f"the UDP receive buffer is limited to {limit} bytes (net.core.rmem_max), less than one {frame_bytes}-byte "
        f"input frame: best-effort frames are lost, uncounted, whenever the receiver falls behind; fix: "
        f"sudo sysctl -w net.core.rmem_max={want} (and in /etc/sysctl.d/ to keep it)"
    )
