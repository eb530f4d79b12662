"""The paper harness's timers: the CUDA-event timer, driven by stand-in events (the real ones need a GPU), calls the
work once per sample between a start and an end record, waits for the end, and reports the median; the host timer
times each step from its call, or from the moment the step says its latency starts."""

from __future__ import annotations

import pytest
import torch

from vpengine.bench.common import event_ms
from vpengine.bench.paper import harness


def test_event_ms_is_the_median_of_one_sample_per_call(monkeypatch):
    log: list[str] = []
    samples = iter([5.0, 1.0, 3.0, 100.0, 2.0])

    class Event:
        def __init__(self, enable_timing: bool) -> None:
            assert enable_timing

        def record(self) -> None:
            log.append("record")

        def synchronize(self) -> None:
            log.append("sync")

        def elapsed_time(self, end: Event) -> float:
            return next(samples)

    monkeypatch.setattr(torch.cuda, "Event", Event)
    ms = event_ms(lambda: log.append("run"), 5)
    assert ms == 3.0  # the median: one slow sample does not move it
    assert log == ["record", "run", "record", "sync"] * 5


def test_timed_counts_from_the_time_a_step_returns(monkeypatch):
    class Clock:  # a clock the steps advance: the test asserts arithmetic, not how a busy machine sleeps
        now = 0.0

        @classmethod
        def perf_counter(cls) -> float:
            return cls.now

    monkeypatch.setattr(harness, "time", Clock)

    def step(i: int) -> float | dict[str, int]:
        Clock.now += 0.020  # e.g. writing the frame into its slot: not latency
        start = Clock.now
        Clock.now += 0.010
        return start if i % 2 else {"outputs": 1}  # odd steps say where their latency starts; others return data

    out = harness.timed(step, 20, warmup=2)
    expected = [0.010 if i % 2 else 0.030 for i in range(20)]  # odd: from the float they returned; even: from the call
    assert out == pytest.approx(harness.pct(expected) | {"hz": 1e3 / 20.0})
    assert out["p90"] == pytest.approx(30.0) and out["p50"] == pytest.approx(20.0)
