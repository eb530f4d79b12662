"""GPU tests: run on the GPU machine with ``pytest -m gpu tests/gpu``.

Every test in this folder is marked ``gpu`` here as well (a forgotten marker must not make a CUDA test run, and
fail, in the CPU suite, whose default selection is ``-m 'not gpu'``). Tests that need CUDA use the ``require_cuda``
fixture, which skips them with the reason when no CUDA device is visible.
"""

from __future__ import annotations

from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # tryfirst: the marker must be on the items before `-m` deselection looks at them.
    for item in items:
        if Path(str(item.fspath)).resolve().is_relative_to(HERE):
            item.add_marker(pytest.mark.gpu)


@pytest.fixture
def require_cuda() -> None:
    """Skip the test, saying why, unless a CUDA device is visible to PyTorch."""
    import torch

    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU (run on the GPU machine: pytest -m gpu tests/gpu)")


@pytest.fixture
def inductor_in_process(monkeypatch):  # type: ignore[no-untyped-def]
    """Inductor's parallel compile starts a pool of worker processes that lives as long as the process that compiled;
    the suite's leak check (no child process may outlive a test) would flag it. Compile in-process here and, via the
    environment, in engine workers."""
    import torch._inductor.config as inductor_config

    monkeypatch.setenv("TORCHINDUCTOR_COMPILE_THREADS", "1")
    with inductor_config.patch(compile_threads=1):
        yield


SLEEP_CYCLES = 5_000_000  # a few ms of device time


class SlowOnDevice:
    """A model's executor with a device-side delay (a ``torch.cuda._sleep`` kernel) queued after the model, before
    the worker copies its outputs into the output slot: however the model itself syncs with the host, the slot is
    written only this long after its work is queued (and, handed off by event, published). Never slot-bound (the
    worker copies)."""

    def __init__(self, inner, cycles: int = SLEEP_CYCLES) -> None:  # type: ignore[no-untyped-def]
        self.inner, self.output_spec, self.cycles = inner, inner.output_spec, cycles

    def __call__(self, inputs):  # type: ignore[no-untyped-def]
        import torch

        out = self.inner(inputs)
        torch.cuda._sleep(self.cycles)
        return out

    def bind(self, inputs, outputs) -> bool:  # type: ignore[no-untyped-def]
        return False

    def held_bytes(self) -> int:
        return self.inner.held_bytes()


def _slow(monkeypatch, slow, cycles: int = SLEEP_CYCLES) -> None:  # type: ignore[no-untyped-def]
    import vpengine.backends as backends

    plain = backends.make_executor

    def make(model, backend, device, name, **kw):  # type: ignore[no-untyped-def]
        ex = plain(model, backend, device, name, **kw)
        return SlowOnDevice(ex, cycles) if slow(name) else ex

    monkeypatch.setattr(backends, "make_executor", make)


@pytest.fixture
def slow_foundation(monkeypatch):  # type: ignore[no-untyped-def]
    """Engines built while this is active get a SlowOnDevice foundation executor."""
    _slow(monkeypatch, lambda name: name == "foundation")


@pytest.fixture
def slow_heads(monkeypatch):  # type: ignore[no-untyped-def]
    """Engines built while this is active get a SlowOnDevice executor for every head."""
    _slow(monkeypatch, lambda name: name != "foundation")


@pytest.fixture
def very_slow_heads(monkeypatch):  # type: ignore[no-untyped-def]
    """Every head's work sleeps about 0.1 s on the device (200 million cycles) after its model."""
    _slow(monkeypatch, lambda name: name != "foundation", 200_000_000)
