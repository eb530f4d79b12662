"""Checks of the public API's scalar arguments: frame ids, timestamps, timeouts, rates and priorities.

Each returns the value as the engine stores it or raises ValueError naming the value and what is accepted, before
the engine takes anything (a slot, a lock) that the error would leave behind. Python and numpy numbers are taken
alike; booleans, NaN and infinity are not (``True`` is not 1 Hz, a NaN capture time is no time at all).
"""

from __future__ import annotations

import math
import numbers
import operator
from collections.abc import Callable
from typing import Any

#: Frame ids are stored as int64; the largest is kept free for the id after it (``submit`` without an id).
FRAME_ID_MIN, FRAME_ID_MAX = -(2**63), 2**63 - 2


def _real(value: Any) -> float | None:
    """``value`` as a float if it is a real number (not a bool), else None."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return None
    return float(value)


def frame_id(value: Any) -> int | None:
    """A frame id given to ``submit``/``frame_slot``: None, or an integer (Python or numpy) that fits int64."""
    if value is None:
        return None
    if isinstance(value, bool):
        raise ValueError(f"frame_id must be an integer, got {value!r}")
    try:
        fid = operator.index(value)
    except TypeError:
        raise ValueError(f"frame_id must be an integer, got {value!r} ({type(value).__name__})") from None
    if not FRAME_ID_MIN <= fid <= FRAME_ID_MAX:
        raise ValueError(f"frame_id must be from {FRAME_ID_MIN} to {FRAME_ID_MAX} (int64), got {fid}")
    return fid


def names(value: Any, what: str) -> list[str] | None:
    """The names an API call takes (``heads=``): None, one str (a list of one), or any collection of str (a list,
    tuple, set, dict keys); not an empty one, which would name nothing (None is the default: all of them)."""
    if value is None:
        return None
    if isinstance(value, str):
        return [value]
    items = None if isinstance(value, (bytes, bytearray)) or not hasattr(value, "__iter__") else list(value)
    if items is None or not all(isinstance(v, str) for v in items):
        raise ValueError(f"{what} must be names (str), one or several, got {value!r}")
    if not items:
        raise ValueError(f"{what}=[] names nothing; leave it out (None) for all")
    return items


def timestamp(value: Any) -> float | None:
    """A capture time in seconds: None (now) or a finite real number."""
    if value is None:
        return None
    t = _real(value)
    if t is None or not math.isfinite(t):
        raise ValueError(f"timestamp must be None or a finite number of seconds, got {value!r}")
    return t


def timeout(value: Any, what: str = "timeout") -> float:
    """A timeout in seconds: a finite real number; one below 0 (a deadline already past, ``deadline - now``) is 0,
    do not wait."""
    t = _real(value)
    if t is None or not math.isfinite(t):
        raise ValueError(f"{what} must be a finite number of seconds, got {value!r}")
    return max(t, 0.0)


#: The bounds of a priority (heads[].priority, cameras[].priority, ``Engine.set_priority``); higher is more important.
MIN_PRIORITY, MAX_PRIORITY = -100, 100


def priority(value: Any, spell: Callable[[Any], str] = repr) -> int:
    """A priority (``Engine.set_priority``): an integer (Python or numpy, not a bool) from MIN_PRIORITY to
    MAX_PRIORITY; higher is more important. ``spell`` writes the value in the message as its door's caller wrote
    it (``json.dumps`` for a JSON body: ``null``, ``"7"``)."""
    try:
        p = None if isinstance(value, bool) else operator.index(value)
    except TypeError:
        p = None
    if p is None or not MIN_PRIORITY <= p <= MAX_PRIORITY:
        raise ValueError(
            f"priority must be an integer from {MIN_PRIORITY} to {MAX_PRIORITY} (higher: more important), "
            f"got {spell(value)}"
        )
    return p


def priority_target(key: str) -> tuple[str | None, str | None]:
    """Whose priority a door's key names (the ROS 2 set_priority topic, the live view's ``/api/priority/<key>``), as
    ``Engine.set_priority`` takes it -> (head, camera): ``head`` (all its cameras), ``head@camera`` (that camera's
    lane only) or ``@camera`` (the camera's own priority: head None). The engine checks the names."""
    if not str(key).strip():
        raise ValueError("the priority's key is empty; give HEAD, HEAD@CAMERA or @CAMERA")
    head, at, camera = str(key).strip().partition("@")
    return head or None, camera if at else None


#: The highest rate limit accepted anywhere (config, ``Engine.set_rate``, ROS 2, the live view): far above any
#: camera, low enough that a typo (an extra zero or three) is caught rather than run.
MAX_RATE_HZ = 10_000.0


def rate(model: str | None, value: Any, spell: Callable[[Any], str] = repr) -> float | None:
    """The one check of a rate limit, for every door that takes one: None (no limit) or a real number from 0 (pause)
    to :data:`MAX_RATE_HZ`. ``model`` names whose rate it is in the message (None: the caller's context does);
    ``spell`` writes values as the door's caller writes them (``json.dumps``: ``null`` for None)."""
    if value is None:
        return None
    hz = _real(value)
    if hz is None or not 0 <= hz <= MAX_RATE_HZ:  # NaN compares False
        whose = "rate" if model is None else f"rate for {model!r}"
        raise ValueError(
            f"{whose} must be {spell(None)} (no limit) or a number of Hz from 0 to {MAX_RATE_HZ:g} (0 pauses), "
            f"got {spell(value)}"
        )
    return hz
