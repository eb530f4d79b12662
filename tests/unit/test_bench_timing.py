"""The CUDA-event timer of the paper harness, driven by stand-in events (the real ones need a GPU): it calls the work
once per sample, between a start and an end record, waits for the end, and reports the median."""

from __future__ import annotations

from types import SimpleNamespace

from vpengine.bench.paper import _event_ms


def test_event_ms_is_the_median_of_one_sample_per_call():
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

    fake_torch = SimpleNamespace(cuda=SimpleNamespace(Event=Event))
    ms = _event_ms(lambda: log.append("run"), 5, fake_torch)
    assert ms == 3.0  # the median: one slow sample does not move it
    assert log == ["record", "run", "record", "sync"] * 5
