"""The control block: per-model rates, states, counters and recent latencies in shared memory.

``Engine.stats()`` reads it and ``Engine.set_rate`` writes it; nothing parses logs. Every field has exactly one
writer (the worker for its counters, the parent for rates and restart counts), and all fields are aligned 8-byte
words, whose loads and stores are single-copy atomic on x86-64 and AArch64, so readers never see half a value and
no lock is needed.

Layout (host memfd)::

    [0, 4)     u32 futex ``stop_word``     bumped at stop: every sleeper wakes
    [4, 8)     u32 futex ``output_word``   bumped by every head publish: ``Engine.results`` sleeps on it
    [8, 16)    i64 stopping flag
    [64, ...)  one entry per model, ENTRY_BYTES each:
                 [0, 4) u32 futex ``control_word`` bumped on rate changes; [8, ...) i64/f64 fields (_FIELDS),
                 then LAT_N f64 compute latencies, LAT_N f64 end-to-end latencies, LAT_N f64 run start times,
                 then ERR_BYTES of UTF-8 text: the last error.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from vpengine.transport import linux
from vpengine.transport.memory import HostRegion
from vpengine.transport.region import RegionHandle

LAT_N = 512
#: Longest sleep of any wait in a worker or the engine: how soon a sleeper notices a stop and beats its heartbeat.
POLL_S = 0.5
ERR_BYTES = 2048
_HEADER = 64
_FIELDS = [
    # name, kind: "q" int64 or "d" float64
    ("state", "q"),
    ("pid", "q"),
    ("runs", "q"),
    ("skipped", "q"),
    ("dropped", "q"),
    ("errors", "q"),
    ("restarts", "q"),
    ("crashes", "q"),
    ("lat_count", "q"),
    ("last_frame_id", "q"),
    ("mps_active", "q"),
    # Note [Answered frames]: the input-ring seq (origin) of the newest frame this model is done with, run or
    # skipped, and of the newest it ran
    ("decided", "q"),
    ("last_run", "q"),
    # Note [Cameras] in worker.py: frames that came after their batch's window (run in the next batch) and frames
    # the least important lane left for a later batch while the model could not keep up, and frames that ran in one
    # model call with another camera's; and the model calls, counted on the lane of each call's first frame (runs /
    # batches: the mean batch)
    ("late", "q"),
    ("deferred", "q"),
    ("batched", "q"),
    ("batches", "q"),
    ("target_hz", "d"),  # NaN: unlimited
    ("heartbeat", "d"),  # time.monotonic() of the last loop iteration; while loading, of the build's last step
    # Note [Start progress] in supervisor.py: the steps of the model's build done and to do (0, 0: not counted)
    ("build_done", "q"),
    ("build_total", "q"),
    ("started_at", "d"),
    ("device_mem_bytes", "d"),
    # Note [Give way] in governor.py: the lane's priority (its head's; the foundation's: its most important
    # consumer's) and its camera's (parent-written), the governor's throttle cap (NaN: none), the skipped frames by
    # reason (they sum to ``skipped``) and the outputs later than the lane's deadline (1 / target rate)
    ("priority", "q"),
    ("camera_priority", "q"),
    # runtime/priority.py: the CUDA stream priority the model's worker runs at, steps above the default
    # (governor-written, the same in every lane of a model)
    ("stream_level", "q"),
    ("cap_hz", "d"),
    ("skipped_rate", "q"),
    ("skipped_priority", "q"),
    ("skipped_overload", "q"),
    ("deadline_misses", "q"),
]
#: Why a frame a model was offered did not run (``ControlBlock.skip``): its own rate limit held it back, the
#: governor's cap for a more important lane did, or it never saw it (busy: a newer frame replaced it).
SKIP_REASONS = ("rate", "priority", "overload")
_F = {name: (1 + i, kind) for i, (name, kind) in enumerate(_FIELDS)}  # word index inside an entry (word 0: futex)
_LAT0 = 1 + len(_FIELDS)
ENTRY_WORDS = _LAT0 + 3 * LAT_N + ERR_BYTES // 8
ENTRY_BYTES = ENTRY_WORDS * 8


STATES = ["starting", "loading", "ready", "running", "paused", "restarting", "failed", "stopped", "hung"]
STARTING, LOADING, READY, RUNNING, PAUSED, RESTARTING, FAILED, STOPPED, HUNG = range(len(STATES))
#: States of a model that serves no frames now: waiting for its output is pointless (``Engine.wait``). "hung": a
#: thread-mode worker silent past runtime.hang_timeout_s, which cannot be killed (runtime/threads.py).
NOT_SERVING = ("failed", "hung")


@dataclass(frozen=True)
class ControlDesc:
    names: tuple[str, ...]
    region: RegionHandle


def _rate(starts: np.ndarray, now: float, window_s: float) -> float:
    """Runs a second from one entry's sorted run starts over the last ``window_s`` (0 for fewer than two, or none
    lately)."""
    recent = starts[starts >= now - window_s]
    if len(recent) < 2 or now - recent[-1] >= window_s:
        return 0.0
    return (len(recent) - 1) / max(recent[-1] - recent[0], 1e-9)


class ControlBlock:
    def __init__(self, names: list[str] | tuple[str, ...], region: HostRegion) -> None:
        self.names = tuple(names)
        self.index = {n: i for i, n in enumerate(self.names)}
        self._region = region
        mv = memoryview(region.mm)
        self._q = mv.cast("q")
        self._d = mv.cast("d")
        self._u = mv.cast("I")
        self._base = region.address()

    @classmethod
    def create(cls, names: list[str], shared: bool = True) -> ControlBlock:
        region = HostRegion("control", _HEADER + ENTRY_BYTES * len(names))
        cb = cls(names, region)
        for i in range(len(names)):
            cb._set(i, "target_hz", math.nan)
            cb._set(i, "cap_hz", math.nan)
        return cb

    def export(self, fds: list[int]) -> ControlDesc:
        return ControlDesc(self.names, self._region.export(fds))

    @classmethod
    def attach(cls, desc: ControlDesc, fds: list[int]) -> ControlBlock:
        return cls(desc.names, HostRegion.open(desc.region, fds))

    def close(self) -> None:
        for mv in (self._q, self._d, self._u):
            mv.release()
        self._region.close()

    def rename(self, old: str, new: str) -> None:
        """Give entry ``old`` the name ``new`` in this process (a seat taken or given back, Note [Heads at run
        time] in runtime/lanes.py); a process that attaches after it sees the new name."""
        if new in self.index:
            raise ValueError(f"the control block has an entry {new!r} already")
        # new objects, never changed in place: other threads read and iterate them meanwhile
        self.names = tuple(new if n == old else n for n in self.names)
        self.index = {n: i for i, n in enumerate(self.names)}

    def clear(self, name: str) -> None:
        """Zero entry ``name`` as at create (no rate limit, no cap): a seat given back starts afresh. Only while
        no worker writes it."""
        i = self.index[name]
        start = (_HEADER // 8) + i * ENTRY_WORDS
        self._q[start : start + ENTRY_WORDS] = memoryview(bytes(ENTRY_BYTES)).cast("q")
        self._set(i, "target_hz", math.nan)
        self._set(i, "cap_hz", math.nan)

    # ------------------------------------------------------------------------------------------ raw fields
    def _w(self, i: int, name: str) -> tuple[int, str]:
        word, kind = _F[name]
        return (_HEADER // 8) + i * ENTRY_WORDS + word, kind

    def _get(self, i: int, name: str) -> Any:
        w, kind = self._w(i, name)
        return self._q[w] if kind == "q" else self._d[w]

    def _set(self, i: int, name: str, value: float) -> None:
        w, kind = self._w(i, name)
        if kind == "q":
            self._q[w] = int(value)
        else:
            self._d[w] = float(value)

    def _add(self, i: int, name: str, n: int = 1) -> None:
        w, _ = self._w(i, name)
        self._q[w] += n  # single writer per counter: no lock needed

    def get(self, name: str, field: str) -> Any:
        return self._get(self.index[name], field)

    def set(self, name: str, field: str, value: float) -> None:
        self._set(self.index[name], field, value)

    def add(self, name: str, field: str, n: int = 1) -> None:
        self._add(self.index[name], field, n)

    # ---------------------------------------------------------------------------------------- wake words
    def _control_addr(self, i: int) -> int:
        return self._base + _HEADER + i * ENTRY_BYTES

    def _bump(self, byte_off: int) -> None:
        self._u[byte_off // 4] = (self._u[byte_off // 4] + 1) & 0xFFFFFFFF
        linux.futex_wake(self._base + byte_off)

    def wait_control(self, name: str, timeout: float) -> None:
        """Sleep up to ``timeout`` s or until this model's rate changes or the engine stops."""
        i = self.index[name]
        off = _HEADER + i * ENTRY_BYTES
        word = self._u[off // 4]
        if self.stopping:
            return
        linux.futex_wait(self._control_addr(i), word, timeout)

    def output_word(self) -> int:
        return self._u[1]

    def wait_output(self, word: int, timeout: float) -> None:
        """Sleep until any head publishes (the output word moves away from ``word``) or ``timeout``."""
        linux.futex_wait(self._base + 4, word, timeout)

    def notify_output(self) -> None:
        self._bump(4)

    # ------------------------------------------------------------------------------------------- control
    def set_rate(self, name: str, hz: float | None) -> None:
        i = self.index[name]
        self._set(i, "target_hz", math.nan if hz is None else hz)
        self._bump(_HEADER + i * ENTRY_BYTES)

    def wake(self, name: str) -> None:
        """Wake ``name``'s worker from ``wait_control`` (a rate of one of its cameras changed)."""
        self._bump(_HEADER + self.index[name] * ENTRY_BYTES)

    def rate(self, name: str) -> float | None:
        """The rate ``name``'s worker obeys: its target, or the governor's cap where that is lower (Note [Give way]
        in governor.py); None: unlimited, 0: paused."""
        i = self.index[name]
        target, cap = self._get(i, "target_hz"), self._get(i, "cap_hz")
        if math.isnan(cap) or cap >= target:  # NaN target (unlimited): never >=
            return None if math.isnan(target) else target
        return cap

    def target(self, name: str) -> float | None:
        """The rate limit ``set_rate`` or the config set (None: unlimited, 0: paused), whatever the cap."""
        v = self._get(self.index[name], "target_hz")
        return None if math.isnan(v) else v

    def set_cap(self, name: str, hz: float | None) -> None:
        """The governor's throttle cap on ``name`` (None: none). Its worker reads it at its next frame, so no wake."""
        self._set(self.index[name], "cap_hz", math.nan if hz is None else hz)

    def cap(self, name: str) -> float | None:
        v = self._get(self.index[name], "cap_hz")
        return None if math.isnan(v) else v

    def skip(self, name: str, reason: str, n: int = 1) -> None:
        """Count ``n`` frames ``name`` did not run, for ``reason`` (one of SKIP_REASONS) and in ``skipped``."""
        i = self.index[name]
        self._add(i, f"skipped_{reason}", n)
        self._add(i, "skipped", n)

    def held_reason(self, name: str) -> str:
        """Why ``name``'s rate gate holds frames back now: ``priority`` while the governor's cap is below its
        target, else ``rate`` (the gate runs at the lower of the two and cannot tell them apart)."""
        i = self.index[name]
        cap = self._get(i, "cap_hz")
        return "priority" if not math.isnan(cap) and not cap >= self._get(i, "target_hz") else "rate"

    @property
    def stopping(self) -> bool:
        return bool(self._q[1])

    def request_stop(self) -> None:
        self._q[1] = 1
        self._bump(0)
        for i in range(len(self.names)):
            self._bump(_HEADER + i * ENTRY_BYTES)
        self._bump(4)

    def set_state(self, name: str, state: int) -> None:
        self.set(name, "state", state)

    def state(self, name: str) -> str:
        return STATES[self.get(name, "state")]

    def heartbeat(self, name: str) -> None:
        self.set(name, "heartbeat", time.monotonic())

    # ------------------------------------------------------------------------------------------ recording
    def _lat_base(self, i: int) -> int:
        return (_HEADER // 8) + i * ENTRY_WORDS + _LAT0

    def _put_times(self, i: int, run: int, compute_s: float, e2e_s: float) -> None:
        b, k = self._lat_base(i), run % LAT_N
        self._d[b + k] = compute_s
        self._d[b + LAT_N + k] = e2e_s

    def _late(self, i: int, e2e_s: float) -> bool:
        """Whether an output ``e2e_s`` after its frame's submit missed entry ``i``'s deadline: one period of its
        target rate (none without one)."""
        target = self._get(i, "target_hz")
        return target > 0 and e2e_s * target > 1.0  # NaN (unlimited): False

    def record_run(self, name: str, t_start: float, compute_s: float, e2e_s: float, frame_id: int) -> None:
        i = self.index[name]
        n = self._get(i, "lat_count")
        if self._late(i, e2e_s):
            self._add(i, "deadline_misses")
        self._put_times(i, n, compute_s, e2e_s)
        self._d[self._lat_base(i) + 2 * LAT_N + n % LAT_N] = t_start
        self._set(i, "last_frame_id", frame_id)
        self._add(i, "runs")
        self._set(i, "lat_count", n + 1)

    def decide(self, name: str, origin: int, ran: bool, wake: bool = True) -> None:
        """Note [Answered frames]: this model is done with the frame of input seq ``origin`` (``ran``: it published
        an output for it); ``wake`` wakes whoever waits for outputs."""
        i = self.index[name]
        if ran:
            self._set(i, "last_run", origin)
        self._set(i, "decided", origin)  # after last_run: whoever sees this sees that
        if wake:
            self._bump(4)

    def amend_last_run(self, name: str, compute_s: float, e2e_s: float) -> None:
        """Correct the times of the run recorded last (a run counted when its work was queued, timed when done)."""
        i = self.index[name]
        n = self._get(i, "lat_count")
        if n:
            if self._late(i, e2e_s) and not self._late(i, self._d[self._lat_base(i) + LAT_N + (n - 1) % LAT_N]):
                self._add(i, "deadline_misses")  # late only now that the device work is done
            self._put_times(i, n - 1, compute_s, e2e_s)

    def set_error(self, name: str, text: str) -> None:
        i = self.index[name]
        off = ((_HEADER // 8) + i * ENTRY_WORDS + _LAT0 + 3 * LAT_N) * 8
        data = text.encode("utf-8", "replace")[: ERR_BYTES - 1]
        mm = self._region.mm
        mm[off : off + ERR_BYTES] = data + b"\0" * (ERR_BYTES - len(data))

    def last_error(self, name: str) -> str:
        i = self.index[name]
        off = ((_HEADER // 8) + i * ENTRY_WORDS + _LAT0 + 3 * LAT_N) * 8
        raw = bytes(self._region.mm[off : off + ERR_BYTES])
        return raw.split(b"\0", 1)[0].decode("utf-8", "replace")

    # -------------------------------------------------------------------------------------------- reading
    def snapshot(self, name: str, window_s: float = 2.0, cameras: list[str] | None = None) -> dict[str, Any]:
        """Counters, achieved rate over the last ``window_s`` and latency percentiles (ms) for one entry; with
        ``cameras`` (a model's camera entries), the model's over all of them: counters summed, samples pooled."""
        i = self.index[name]
        parts = [name, *(cameras or [])]
        samples = [self._samples(p) for p in parts]
        lat, e2e = (np.concatenate(a) for a in list(zip(*samples))[:2])
        now = time.monotonic()
        # each entry's own rate, summed: the cameras' starts pooled, two frames that came together (a tick of two
        # cameras) a few microseconds apart read as a billion Hz
        achieved = sum(_rate(np.sort(starts), now, window_s) for _, _, starts in samples)
        hb = self._get(i, "heartbeat")

        def pct(a: np.ndarray) -> dict[str, float]:
            if not len(a):
                return {"p50": math.nan, "p90": math.nan, "p99": math.nan, "mean": math.nan}
            p = np.percentile(a, [50, 90, 99]) * 1e3
            return {"p50": float(p[0]), "p90": float(p[1]), "p99": float(p[2]), "mean": float(a.mean() * 1e3)}

        def one(field: str) -> float:  # several cameras' differing values: NaN (stats()["cameras"] has each)
            values = {self._get(self.index[p], field) for p in (cameras or [name])}
            return values.pop() if len(values) == 1 else math.nan

        target, cap = one("target_hz"), one("cap_hz")

        def total(field: str) -> int:
            return int(sum(self._get(self.index[p], field) for p in parts))

        # ``skipped`` as the sum of its reasons, read once: its own counter moves a moment after a reason's, and a
        # reader between the two would see them disagree
        skipped_by = {r: total(f"skipped_{r}") for r in SKIP_REASONS}
        return {
            "state": STATES[self._get(i, "state")],
            "pid": self._get(i, "pid"),
            "target_hz": None if math.isnan(target) else target,
            "achieved_hz": achieved,
            "runs": total("runs"),
            "skipped": sum(skipped_by.values()),
            "skipped_by": skipped_by,
            "deadline_misses": total("deadline_misses"),
            "priority": max(self._get(self.index[p], "priority") for p in (cameras or [name])),
            "cap_hz": None if math.isnan(cap) else cap,
            "camera_priority": None if math.isnan(cam_priority := one("camera_priority")) else int(cam_priority),
            "dropped": total("dropped"),
            "late": total("late"),
            "deferred": total("deferred"),
            "batched": total("batched"),
            "batches": total("batches"),
            "errors": self._get(i, "errors"),
            "restarts": self._get(i, "restarts"),
            "crashes": self._get(i, "crashes"),
            "last_frame_id": self._get(i, "last_frame_id"),
            "heartbeat_age_s": (now - hb) if hb > 0 else None,
            "latency_ms": pct(lat),
            "e2e_latency_ms": pct(e2e),
            "mps": bool(self._get(i, "mps_active")),
            "device_mem_bytes": self._get(i, "device_mem_bytes"),
            "last_error": self.last_error(name) or None,
        }

    def _samples(self, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """An entry's recent compute latencies, end-to-end latencies and run start times (copies). The starts are
        read first: a run's times are written before its start, so a new start read comes with its own times, and a
        slot rewritten between the reads pairs an old start (older than any window asked for) with newer times."""
        i = self.index[name]
        n = min(self._get(i, "lat_count"), LAT_N)
        b = self._lat_base(i)
        starts = np.array(self._d[b + 2 * LAT_N : b + 2 * LAT_N + n])
        return np.array(self._d[b : b + n]), np.array(self._d[b + LAT_N : b + LAT_N + n]), starts

    def recent_runs(self, name: str, since: float) -> tuple[np.ndarray, np.ndarray]:
        """Start times (sorted) and end-to-end latencies of ``name``'s recorded runs that started at or after
        ``since`` (of the last LAT_N)."""
        _, e2e, starts = self._samples(name)
        order = np.argsort(starts)
        keep = order[starts[order] >= since]
        return starts[keep], e2e[keep]

    def recent_latencies(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        i = self.index[name]
        n = min(self._get(i, "lat_count"), LAT_N)
        b = self._lat_base(i)
        return np.asarray(self._d[b : b + n]).copy(), np.asarray(self._d[b + LAT_N : b + LAT_N + n]).copy()
