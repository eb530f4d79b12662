"""Note [First batch] (runtime/worker.py) in a whole engine: every worker's batch of a frame per camera before READY
fits what the engine wires around it (the foundation's frames, a head's feature keys, output slots on the host and
on the device), leaves no trace in what the engine serves and counts, and a head added at run time warms its own,
but a restarted worker does not, into the mailbox it published to. On CUDA only in the product; here on the CPU,
switched on (thread mode: the switch is this process's)."""

from __future__ import annotations

import json

import pytest

from helpers.frames import frame
from helpers.waiting import wait_for
from tests_paths import tiny
from vpengine.engine import Engine
from vpengine.runtime import prepare
from vpengine.runtime.worker import WorkerCore

pytestmark = pytest.mark.timeout(300)

CAMERAS = ["a", "b", "c"]
DET2 = {"name": "det2", "model": "tiny_det"}
FAULTY = "helpers.faulty:FaultyHead"


@pytest.fixture()
def warmed(monkeypatch):
    """The warm batch switched on in this process; each worker's (name, frames it warmed), in order."""
    noted: list[tuple[str, int]] = []
    warm = WorkerCore.warm_batch

    def noting(self, example):  # type: ignore[no-untyped-def]
        n = warm(self, example)
        noted.append((self.name, n))
        return n

    monkeypatch.setattr(prepare, "warms_first_batch", lambda dev: True)
    monkeypatch.setattr(WorkerCore, "warm_batch", noting)
    return noted


def test_every_worker_warms_a_batch_of_every_camera_and_serves_as_before(warmed):
    cfg = tiny("thread", "cameras=[{name: a}, {name: b}, {name: c}]", "runtime.spare_heads=1")
    with Engine(cfg) as e:
        assert sorted(warmed) == [("depth", 3), ("det", 3), ("foundation", 3), ("seg", 3)]
        for k in range(4):
            ids = [e.submit(frame(3 * k + i), camera=c) for i, c in enumerate(CAMERAS)]
            for fid, c in zip(ids, CAMERAS):
                out = e.wait(fid, timeout=60)
                assert sorted(out) == ["depth", "det", "seg"] and all(r.frame_id == fid for r in out.values())
                assert out["depth"].camera == c
        models = e.stats()["models"]
        for m in ("foundation", "depth", "seg", "det"):  # the warm batch is not counted as served
            assert (models[m]["runs"], models[m]["dropped"], models[m]["errors"]) == (12, 0, 0), (m, models[m])
        e.add_head(DET2)  # a fresh seat: warmed
        assert warmed[-1] == ("det2", 3)
        ids = [e.submit(frame(20 + i), camera=c) for i, c in enumerate(CAMERAS)]
        assert all("det2" in e.wait(f, timeout=60) for f in ids)
        e.remove_head("det2")
        e.add_head(DET2)  # its seat again, with a new mailbox: warmed again
        assert warmed[-1] == ("det2", 3)


def test_a_restarted_worker_leaves_the_mailbox_it_published_to_alone(tmp_path, warmed, restart_backoff):
    """Readers may hold its output slots (a borrowed result): no warm batch there."""
    restart_backoff(0.05)
    opts = json.dumps({"raise_at_run": 2, "cuda_error": True, "once_marker": str(tmp_path / "raised")})
    cfg = tiny(
        "thread", "cameras=[{name: a}, {name: b}, {name: c}]", f"heads.seg.model={FAULTY}", f"heads.seg.options={opts}"
    )
    with Engine(cfg) as e:
        assert ("seg", 3) in warmed
        for k in range(2):  # seg's second run raises a CUDA error: its worker is restarted
            for i, c in enumerate(CAMERAS):
                e.wait(e.submit(frame(3 * k + i), camera=c), timeout=60)
        wait_for(
            lambda: e.stats()["models"]["seg"]["restarts"] == 1 and e.stats()["models"]["seg"]["state"] == "running",
            timeout=30,
            what="seg restarted",
        )
        assert warmed[-1] == ("seg", 0) and [w for w in warmed if w[0] == "seg"] == [("seg", 3), ("seg", 0)]
        fid = e.submit(frame(50), camera="b")
        assert "seg" in e.wait(fid, timeout=60)  # and it serves
