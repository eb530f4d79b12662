"""`vpengine bench` end to end on the CPU with the tiny models: the harness that produced the GPU results runs, writes
results a report can read, and refuses bad arguments by name."""

from __future__ import annotations

import json
import math

import pytest
from test_cli import vpengine

pytestmark = pytest.mark.timeout(420)

PNG = b"\x89PNG\r\n\x1a\n"


def test_paper_harness_e1_and_floor_then_report(tmp_path):
    p = vpengine(
        "bench", "paper", "--tiny", "--device", "cpu", "--experiments", "E1,floor", "--heads", "1,2",
        "--frames", "5", "--floor-heads", "depth,seg", "--tag", "smoke", "--out", str(tmp_path), timeout=400,
    )  # fmt: skip
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    res = json.loads((tmp_path / "paper_cpu_smoke.json").read_text())
    assert res["setup"]["backbone"] == "tiny_vit" and res["setup"]["device"] == "cpu"
    rows = res["E1"]["rows"]
    assert [r["heads"] for r in rows] == [1, 2]
    for r in rows:
        for kind in ("engine", "independent", "sequential"):
            assert r[kind]["n"] == 5 and 0 < r[kind]["p50"] <= r[kind]["p99"], (kind, r[kind])
        assert math.isclose(r["speedup_vs_independent"], r["independent"]["mean"] / r["engine"]["mean"])
    floor = res["floor"]
    assert floor["device_ms"] == {}  # no CUDA events on the CPU: no floor is claimed
    assert "floor_sum_ms" not in floor and floor["chained_ms"] == {}
    assert floor["thread"]["n"] == 5 and floor["process"]["n"] == 5
    assert (tmp_path / "paper_cpu_smoke.png").read_bytes().startswith(PNG)

    r = vpengine("bench", "report", "--results", str(tmp_path))
    assert r.returncode == 0, r.stderr[-3000:]
    md = (tmp_path / "summary.md").read_text()
    e1 = [line for line in md.splitlines() if line.startswith("| E1")]
    assert len(e1) == 1 and "2 depth heads (tiny_vit, eager)" in e1[0] and "paper_cpu_smoke.json" in e1[0], md
    assert "floor" not in md  # the CPU run has no device-time floor to report
    assert (tmp_path / "summary.png").read_bytes().startswith(PNG)


def test_paper_harness_names_a_bad_floor_head(tmp_path):
    p = vpengine(
        "bench", "paper", "--tiny", "--device", "cpu", "--experiments", "floor", "--floor-heads", "depth,sky",
        "--out", str(tmp_path),
    )  # fmt: skip
    assert p.returncode != 0
    assert "sky" in p.stderr and "accepted are depth, seg, det" in p.stderr, p.stderr[-2000:]


def test_paper_harness_thread_mode_is_recorded_and_reported(tmp_path):
    p = vpengine(
        "bench", "paper", "--tiny", "--device", "cpu", "--experiments", "E1,E2", "--heads", "2", "--frames", "3",
        "--mode", "thread", "--results", "borrow", "--tag", "thread", "--out", str(tmp_path), timeout=300,
    )  # fmt: skip
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    assert "E1 N=2: engine (thread mode, MPS off, results borrow)" in p.stdout
    assert "E2 N=2: engine (thread mode, MPS off, results borrow)" in p.stdout
    res = json.loads((tmp_path / "paper_cpu_thread.json").read_text())
    assert res["setup"]["mode"] == "thread" and res["setup"]["mps"] == "off"
    assert res["setup"]["results"] == "borrow"
    for key in ("E1", "E2"):
        (row,) = res[key]["rows"]
        assert row["heads"] == 2 and row["engine"]["n"] == 3 and row["sequential"]["n"] == 3
    r = vpengine("bench", "report", "--results", str(tmp_path))
    assert r.returncode == 0, r.stderr[-3000:]
    md = (tmp_path / "summary.md").read_text()
    assert "| E1 shared backbone + 2 depth heads (tiny_vit, eager, thread mode, borrowed results) |" in md, md
    assert "| E2 2 detection heads (tiny_vit, eager, thread mode, borrowed results) |" in md, md
