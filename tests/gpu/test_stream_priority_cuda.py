"""Note [Stream priority at run time] (runtime/device.py) on CUDA: a priority changed at run time moves a worker's
runs to a stream of that priority, ordered after what it queued before. Run on the GPU machine: ``pytest -m gpu
tests/gpu``."""

from __future__ import annotations

import time

import pytest
import torch

from helpers.frames import frame
from helpers.models import StreamNotingDepth
from tests_paths import tiny
from vpengine.engine import Engine
from vpengine.runtime.device import DeviceContext

pytestmark = [pytest.mark.gpu, pytest.mark.timeout(300), pytest.mark.usefixtures("require_cuda")]


def test_a_device_context_moved_to_another_level_runs_after_what_it_queued_and_keeps_each_stream():
    dev = DeviceContext("cuda", priority=0)
    x = torch.zeros(1 << 20, device="cuda")
    before = torch.cuda.current_stream()
    with dev.active():
        torch.cuda._sleep(300_000_000)  # ~0.15 s of the old stream busy before the write
        x.fill_(1.0)
        old = dev.stream
        assert old is not None
        assert dev.use_level(1)
        assert dev.stream is not old and dev.stream.priority < old.priority  # CUDA: lower is more urgent
        assert torch.cuda.current_stream() == dev.stream  # current from the move on
        y = x.clone()  # queued on the new stream: must see the old stream's write
        dev.complete()
        assert bool((y == 1).all())
        assert not dev.use_level(1)  # already there
        assert dev.use_level(0) and dev.stream is old  # kept for a return
    assert torch.cuda.current_stream() == before  # active() put back what was current


@pytest.mark.parametrize("foundation", ["eager", "compile"])  # compile: slot-bound, launched by submit
def test_set_priority_moves_a_thread_mode_models_runs_to_a_stream_of_higher_priority_and_back(foundation, monkeypatch):
    """depth's runs (and, compiled, the foundation model's, launched by the submitting thread on the foundation
    worker's stream) move up when depth is raised, and back."""
    import vpengine.backends.compiled as compiled

    launched: list[int] = []  # the foundation's launches: the priority of the stream each went to
    on, bound = compiled.CompiledExecutor.run_bound_on, compiled.CompiledExecutor.run_bound

    def run_bound_on(self, stream, i, o):  # type: ignore[no-untyped-def]
        if self.name == "foundation":
            launched.append(stream.priority)
        return on(self, stream, i, o)

    def run_bound(self, i, o):  # type: ignore[no-untyped-def]
        if self.name == "foundation":
            launched.append(torch.cuda.current_stream().priority)
        return bound(self, i, o)

    monkeypatch.setattr(compiled.CompiledExecutor, "run_bound_on", run_bound_on)
    monkeypatch.setattr(compiled.CompiledExecutor, "run_bound", run_bound)
    cfg = tiny(
        "thread",
        "device=cuda",
        "heads.depth.model=helpers.models:StreamNotingDepth",
        f"foundation_model.backend={foundation}",
    )
    StreamNotingDepth.priorities.clear()
    depth = StreamNotingDepth.priorities
    with Engine(cfg) as e:
        fid = 0

        def runs_until(pred) -> bool:  # type: ignore[no-untyped-def]
            nonlocal fid
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:
                res = e.wait(e.submit(frame(fid)), timeout=30)
                fid += 1
                assert "depth" in res  # (the others may give way while depth is raised)
                if pred():
                    return True
            return False

        runs_until(lambda: True)
        base = depth[-1]
        e.set_priority("depth", 5)
        assert runs_until(lambda: depth[-1] < base), depth[-5:]
        higher = depth[-1]
        if foundation == "compile":  # its level follows its most important head's
            assert runs_until(lambda: launched[-1] == higher), launched[-5:]
        e.set_priority("depth", 0)
        assert runs_until(lambda: depth[-1] == base), depth[-5:]
        if foundation == "compile":
            assert runs_until(lambda: launched[-1] == base), launched[-5:]
            assert e.stats()["engine"]["launched_by_submit"] > 0  # moves beside the inline launch
        e.set_priority("depth", 5)
        assert runs_until(lambda: depth[-1] == higher)
        assert all(m["errors"] == 0 for m in e.stats()["models"].values())
