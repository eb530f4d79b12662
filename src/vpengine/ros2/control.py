"""Steering from ROS 2: rate and priority commands (parsed from text, or numbers from services and parameters), the
model-names text, and the control thread that applies them and publishes /diagnostics (Note [Control path]). No
middleware here.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Protocol

from vpengine import checks
from vpengine.ros2.diagnostics import DiagnosticsOut
from vpengine.ros2.heads import HEAD_COMMANDS, HeadCommands

log = logging.getLogger("vpengine.ros2")

#: Rate values (case-insensitive) that mean "no limit", in rate commands.
UNLIMITED_WORDS = ("max", "none", "null", "unlimited", "inf", "-1")


# ------------------------------------------------------------------------------------------- rate commands
def parse_rate(text: str) -> float | None:
    """A rate from a command: Hz as a number from 0 to checks.MAX_RATE_HZ (``"5"``, ``"2.5"``; ``"0"`` pauses), or
    one of UNLIMITED_WORDS for no limit. Raises ValueError naming the bad value and what is accepted."""
    t = str(text).strip().lower()
    if t in UNLIMITED_WORDS:
        return None
    try:
        hz = float(t)
    except ValueError:
        hz = math.nan
    if not math.isfinite(hz) or not 0 <= hz <= checks.MAX_RATE_HZ:
        raise ValueError(
            f"rate {text!r} is not a rate; accepted: a number of Hz from 0 to {checks.MAX_RATE_HZ:g} (0 pauses) or "
            f"one of {', '.join(UNLIMITED_WORDS)} (no limit)"
        )
    return hz


def numeric_rate(hz: float | None) -> float | None:
    """A rate as services and parameters carry it, a number: Hz >= 0 (0 pauses); None, a negative number or inf for
    no limit. Raises ValueError for NaN."""
    if hz is None:
        return None
    hz = float(hz)
    if math.isnan(hz):
        raise ValueError(f"rate {hz} is NaN; accepted: Hz >= 0 (0 pauses), or a negative number or inf for no limit")
    return None if hz < 0 or math.isinf(hz) else hz


def parse_rate_command(
    key: str, value: str | float | None, models: Sequence[str], cameras: Sequence[str] = ()
) -> tuple[str, float | None]:
    """A rate command -> (key, Hz or None). ``value`` is text as the set_rate topic carries it (diagnostic_msgs/
    KeyValue ``{key: model, value: rate}``, :func:`parse_rate`) or a number as services carry it
    (:func:`numeric_rate`). ``key`` may be ``model@camera``: that model's rate for one of ``cameras`` alone
    (:func:`model_at` splits it)."""
    model_at(key, models, cameras)
    hz = parse_rate(value) if isinstance(value, str) else numeric_rate(value)
    # the one rate check, "no limit" spelled as a service's number writes it: a number past the cap
    checks.rate(str(key).strip(), hz, spell=lambda v: "a negative number or inf" if v is None else repr(v))
    return str(key).strip(), hz


def model_at(key: str, models: Sequence[str], cameras: Sequence[str] = ()) -> tuple[str, str | None]:
    """``model`` or ``model@camera`` -> (model, camera or None: all its cameras); ValueError naming the models or
    cameras when either is unknown."""
    model, at, camera = str(key).strip().partition("@")
    if model not in models:
        raise ValueError(f"rate command for unknown model {key!r}; models: {', '.join(models)}")
    if at and camera not in cameras:
        raise ValueError(
            f"rate command {key!r} names no camera of this engine; cameras: {', '.join(cameras) or '(none)'}"
        )
    return model, camera if at else None


# --------------------------------------------------------------------------------------- priority commands
def parse_priority(value: str | int) -> int:
    """A priority from a command: an integer from checks.MIN_PRIORITY to MAX_PRIORITY, as text (the set_priority
    topic: ``"10"``, ``"-5"``) or a number (parameters). Raises ValueError naming the bad value and the range."""
    if isinstance(value, str):
        try:
            return checks.priority(int(value.strip()))
        except ValueError:
            pass  # not an integer, or out of range: one message for both, naming the text as given
    return checks.priority(value)


def model_names_text(names: Iterable[str]) -> str:
    """The model-names topic's text: a JSON list, e.g. ``["foundation", "depth", "seg", "det"]``."""
    return json.dumps(list(names))


class Steered(Protocol):
    """What :class:`ControlLoop` uses of :class:`vpengine.ros2.core.Ros2Core`."""

    def set_rate(self, key: str, value: str) -> tuple[str, float | None]: ...

    def set_priority(self, key: str, value: str) -> tuple[str, int]: ...

    def diagnostics(self) -> DiagnosticsOut: ...


# ------------------------------------------------------------------------------------------- control path
class ControlLoop:
    """Note [Control path]: commands and /diagnostics have a thread of their own, shared by every transport.

    On the output thread they waited behind the writes of 8 MB images (a reliable write can block until a slow
    reader acknowledges): at 1080p /diagnostics went silent for 3-17 s, longer than diagnostic_aggregator's stale
    timeout, and rate commands, wanted most when the machine is overloaded, waited as long. This loop waits only for
    commands (``wait_commands(timeout)`` returns the (kind, key, value) triples that arrived, kind ``rate`` from
    the set_rate topic, ``priority`` from set_priority, ``add_head`` or ``remove_head`` (key empty), waiting at most
    ``timeout`` s), applies each at once and publishes diagnostics right after it (the change is seen, and the
    diagnostics' stamp says when it was applied), and otherwise publishes diagnostics every ``period_s`` on a fixed
    schedule. It touches the engine only through
    ``set_rate``, ``set_priority`` and ``stats`` (shared-memory writes and reads), so it never waits for a frame or
    a result. ``before_diagnostics`` lets the transport refresh what only it knows (the input link: matched
    publishers, receive buffer) first. Head commands (kinds ``add_head``, ``remove_head``) take seconds, so this
    loop only hands them to ``heads`` (Note [Head commands] in :mod:`vpengine.ros2.heads`).
    """

    def __init__(
        self,
        core: Steered,
        publish: Callable[[DiagnosticsOut], None],
        wait_commands: Callable[[float], Iterable[tuple[str, str, str]]],
        *,
        period_s: float = 1.0,
        before_diagnostics: Callable[[], None] | None = None,
        heads: HeadCommands | None = None,
    ) -> None:
        if not period_s > 0:
            raise ValueError(f"diagnostics period must be > 0 s, got {period_s}")
        self.core, self.publish, self.wait_commands = core, publish, wait_commands
        self.period_s = period_s
        self.before_diagnostics = before_diagnostics
        self.heads = heads

    def diagnostics_now(self) -> None:
        if self.before_diagnostics is not None:
            self.before_diagnostics()
        self.publish(self.core.diagnostics())

    def run(self, stop: threading.Event) -> None:
        """Until ``stop`` is set."""
        next_at = time.monotonic()
        while not stop.is_set():
            applied = False
            for kind, key, value in self.wait_commands(max(0.0, min(next_at - time.monotonic(), 0.2))):
                if kind in HEAD_COMMANDS and self.heads is not None:
                    self.heads.put(kind, value)  # the head thread logs and publishes its outcome
                    continue
                apply = {"rate": self.core.set_rate, "priority": self.core.set_priority}[kind]
                try:
                    apply(key, value)
                    applied = True
                except ValueError as e:
                    log.warning("%s command {key: %r, value: %r} ignored: %s", kind, key, value, e)
            now = time.monotonic()
            if applied or now >= next_at:
                self.diagnostics_now()
                # a fixed schedule; after a command (or a stall longer than a period) a period from now
                next_at = now + self.period_s if applied or now - next_at > self.period_s else next_at + self.period_s
