"""`vpengine bench paper` end to end on the CPU with the tiny models (configs/tiny.yaml), the harness that produces the
GPU results: every experiment that runs off CUDA writes its results, `--set` reaches the engine, `vpengine bench
report` reads what it wrote, and the GPU scripts run their CPU equivalents (release.sh's stages, compare.sh's
before/after with its report)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import pytest
from test_cli import vpengine

from tests_paths import ROOT

pytestmark = pytest.mark.timeout(420)

PNG = b"\x89PNG\r\n\x1a\n"


def test_paper_runs_every_cpu_experiment_and_the_report_reads_them(tmp_path, cli):
    # thread mode: the engines E1 to E5 build start no processes (E1's independent models and the floor's process
    # mode still do), which is most of this test's time on a small machine; the harness is the same in either mode
    p = vpengine(
        "bench", "paper", "--config", "configs/tiny.yaml", "--set", "mode=thread", "--experiments", "E1,E2,E4,E5,floor",
        "--heads", "1,2", "--frames", "5", "--e4-seconds", "3", "--e5-frames", "60", "--floor-heads", "depth,seg",
        "--floor-batches", "1,2", "--tag", "smoke", "--out", str(tmp_path),
        timeout=400,
    )  # fmt: skip
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    assert [f.name for f in tmp_path.iterdir()] == ["paper_cpu_smoke.json"]  # figures are the report's
    res = json.loads((tmp_path / "paper_cpu_smoke.json").read_text())
    assert res["machine"]["cores"] >= 1 and res["setup"]["config"] == "configs/tiny.yaml"
    assert res["setup"]["backbone"] == "tiny_vit" and res["setup"]["device"] == "cpu"
    for key in ("E1", "E2"):
        rows = res[key]["rows"]
        assert [r["heads"] for r in rows] == [1, 2]
        for r in rows:
            kinds = ("engine", "sequential", "independent") if key == "E1" else ("engine", "sequential")
            for kind in kinds:
                assert r[kind]["n"] == 5 and 0 < r[kind]["p50"] <= r[kind]["p99"], (kind, r[kind])
            assert r["device_ms"] == {}  # no CUDA events on the CPU
    r = res["E1"]["rows"][1]
    assert math.isclose(r["speedup_vs_independent"], r["independent"]["mean"] / r["engine"]["mean"])
    e4 = res["E4"]
    assert [x["rate_hz"] for x in e4["rows"]] == [5, 10, 15, 20, 25, 30] and e4["input_seconds"] == 3
    # never above the limit; below it only if this machine (shared, 2 cores) was too busy to keep up
    assert all(0 < x["runs"] <= x["ideal"] + 1 for x in e4["rows"]), e4["rows"]
    e5 = res["E5"]
    assert e5["frames"] == 60 and set(e5["per_head_latency_ms"]) == {"depth", "seg", "det"}
    assert e5["all_three_latency_ms"]["n"] > 0 and e5["memory_flat"] is None  # no device memory on the CPU
    assert 0 < e5["cpu_cores"] < 4 and 0 < res["E1"]["rows"][0]["engine"]["cpu_cores"] < 4
    assert res["setup"]["frame_size"] == [160, 120]  # the config's input size
    floor = res["floor"]
    assert floor["heads"] == ["depth", "seg"] and floor["device_ms"] == {} and "floor_sum_ms" not in floor
    assert "by_batch" not in floor  # device times by batch size: CUDA only
    for key in ("thread", "process", "thread_frame_slot", "process_frame_slot"):
        assert floor[key]["n"] == 5, key

    r = cli("bench", "report", "--results", str(tmp_path), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr[-3000:]
    md = (tmp_path / "summary.md").read_text()
    assert "Machine: " in md and "-core" in md
    label = "(tiny_vit, eager, 120x160"
    for start in ("| E1 shared backbone + 2 depth heads ", "| E2 2 detection heads ", "| E4 rate limits, 3 s ",
                  "| E5 60 frames at 30 Hz, depth+seg+det ", "| engine vs device-time floor "):  # fmt: skip
        (line,) = [x for x in md.splitlines() if x.startswith(start)]
        assert label in line and line.endswith("| paper_cpu_smoke.json |"), line
    assert (tmp_path / "summary.png").read_bytes().startswith(PNG)


def test_set_reaches_the_engine_and_the_report_labels_it(tmp_path, cli):
    p = cli(
        "bench", "paper", "--config", "configs/tiny.yaml", "--set", "mode=thread", "--experiments", "E2",
        "--heads", "2", "--frames", "3", "--results", "borrow", "--tag", "thread", "--out", str(tmp_path),
        "--frame-size", "200x90",
    )  # fmt: skip
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    assert "E2 N=2: engine (thread mode, MPS auto, results borrow)" in p.stdout
    res = json.loads((tmp_path / "paper_cpu_thread.json").read_text())
    assert res["setup"]["mode"] == "thread" and res["setup"]["overrides"] == ["mode=thread"]
    assert res["setup"]["frame_size"] == [200, 90]  # frames of another size than the 160x120 canvas
    r = cli("bench", "report", "--results", str(tmp_path), "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr[-3000:]
    md = (tmp_path / "summary.md").read_text()
    label = "(tiny_vit, eager, 120x160, 200x90 frames (boundary), thread mode, borrowed results)"
    assert f"| E2 2 detection heads {label} |" in md, md


def test_cheap_benches_and_the_report_write_a_new_folder_of_their_own_by_default(tmp_path, cli):
    tracked = {p: p.stat().st_mtime_ns for p in (ROOT / "benchmarks" / "results").rglob("*") if p.is_file()}
    # the cheapest for real (every bench's default folder: tests/unit/test_bench_out.py)
    p = vpengine("bench", "hop", "--hops", "30", "--mbytes", "0.01", cwd=tmp_path, timeout=300)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    (hop,) = tmp_path.glob("bench-hop-*")
    assert sorted(f.name for f in hop.iterdir()) == ["hop_cpu.json", "hop_cpu.png"]
    r = cli("bench", "report", "--results", str(hop), cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    (report,) = tmp_path.glob("bench-report-*")
    assert sorted(f.name for f in report.iterdir()) == ["summary.md", "summary.png"]
    assert (report / "summary.md").read_text().startswith(f"# vpengine benchmarks: {hop.name}")
    assert sorted(f.name for f in hop.iterdir()) == ["hop_cpu.json", "hop_cpu.png"]  # the results, only read
    now = {p: p.stat().st_mtime_ns for p in (ROOT / "benchmarks" / "results").rglob("*") if p.is_file()}
    assert now == tracked  # the clone's results untouched


def test_a_bad_override_is_named(tmp_path, cli):
    p = cli(
        "bench", "paper", "--config", "configs/tiny.yaml", "--set", "mode=sideways", "--experiments", "E1",
        "--out", str(tmp_path),
    )  # fmt: skip
    assert p.returncode != 0
    assert "mode" in p.stderr and "sideways" in p.stderr, p.stderr[-2000:]


def _script(name: str, *args: str, **env: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHON": sys.executable, "CONFIG": "configs/tiny.yaml", **env}
    cmd = ["bash", f"benchmarks/gpu/{name}", *args]
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=400)


def test_release_script_stages_run_the_paper_and_the_report(tmp_path):
    # thread mode: the engine starts no processes (E1's independent model still does); the stages are the subject
    p = _script(
        "release.sh", "e1", "report", "--", "--heads", "1", "--frames", "3", "--set", "mode=thread", OUT=str(tmp_path)
    )
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-2000:]
    assert "E1 N=1: engine" in p.stdout
    assert sorted(f.name for f in tmp_path.iterdir()) == [
        "paper_cpu_e1.json",
        "release.log",
        "summary.md",
        "summary.png",
    ]
    assert "paper_cpu_e1.json |" in (tmp_path / "summary.md").read_text()
    bad = _script("release.sh", "e9", OUT=str(tmp_path))
    assert bad.returncode == 2 and "unknown stage e9; accepted: tests tests1 tests2 tests3 integration e1" in bad.stdout


def test_release_scripts_gpu_test_parts_run_every_gpu_test_once(tmp_path):
    # the parts fit a call each on an empty compile cache; a gpu test in none of them, or in two, would go unrun or
    # cost a call twice. --collect-only lists what each part selects, without a GPU (-qq against the stage's -v: one
    # test id a line).
    p = _script("release.sh", "tests", OUT=str(tmp_path), PYTEST_ARGS="--collect-only -qq")
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-2000:]
    parts: list[list[str]] = []
    for line in (tmp_path / "gpu_tests.log").read_text().splitlines():
        if line.startswith("== gpu tests, part "):
            parts.append([])
        elif "::" in line:
            parts[-1].append(line.strip())
    assert len(parts) == 3 and all(parts), [len(x) for x in parts]
    every = subprocess.run(
        [sys.executable, "-m", "pytest", "-m", "gpu", "tests/gpu", "--collect-only", "-q", "-p", "no:cacheprovider"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    expected = sorted(line for line in every.stdout.splitlines() if "::" in line)
    assert len(expected) > 50, every.stdout[-2000:] + every.stderr[-2000:]
    assert sorted(t for part in parts for t in part) == expected  # each once: a test in two parts would be listed twice
    assert any("bench_cameras" in t for t in parts[2]) and not any("bench_cameras" in t for t in parts[1])


def test_compare_script_runs_both_trees_and_reports_after_against_before(tmp_path):
    p = _script("compare.sh", ".", "E1", OUT=str(tmp_path), HEADS="1", FRAMES="3", MODE="thread")
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-2000:]
    assert p.stdout.count("E1 N=1: engine") == 2
    files = sorted(f.name for f in tmp_path.iterdir())
    assert files == ["paper_cpu_after_e1.json", "paper_cpu_before_e1.json", "summary.md", "summary.png"]
    md = (tmp_path / "summary.md").read_text()
    (line,) = [x for x in md.splitlines() if x.startswith("| E1 | engine, 1 heads, mean |")]
    assert line.endswith("| paper_cpu_after_e1.json |")
    bad = _script("compare.sh", "no-such-tree", OUT=str(tmp_path))
    assert bad.returncode != 0 and "neither a folder with src/vpengine nor a commit" in bad.stderr


def test_cameras_bench_streams_batches_and_compares_with_separate_engines(tmp_path, cli):
    p = cli(
        "bench", "cameras", "-c", "tiny", "--set", "device=cpu", "--set", "mode=thread", "--stream-cameras", "2",
        "--seconds", "1",
        "--cameras", "1,2", "--rounds", "3", "--point-seconds", "0", "--heads", "depth,seg", "--out", str(tmp_path),
        "--name", "cams",
    )  # fmt: skip
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    res = json.loads((tmp_path / "cams.json").read_text())
    s = res["stream"]
    assert res["mode"] == "thread" and res["heads"] == ["depth", "seg"]
    assert set(s["counted"]) == {"foundation", "depth", "seg"}
    assert s["cameras"] == 2 and 0 < s["frames_all_heads"] <= s["frames_submitted"] and s["workers_on_mps"] == 0
    assert s["memory_report"]["mailbox_host_bytes"] > 0 and "out.depth" in s["memory_report"]["mailboxes"]
    assert s["counted"]["foundation"]["batched"] > 0  # two synchronised cameras: the backbone ran them together
    assert 0 < s["tick_submit_ms"]["p50"] <= s["tick_submit_ms"]["p99"]  # two submits a tick, a thread each
    # counted over the stream, not the warm-up: every frame submitted then is one the backbone ran or skipped
    fm = s["counted"]["foundation"]
    assert fm["runs"] + fm["skipped"] + fm["dropped"] == s["frames_submitted"], (fm, s["frames_submitted"])
    assert fm["runs"] / 2 <= fm["batches"] <= fm["runs"] and f"mean batch {fm['runs'] / fm['batches']:.1f}" in p.stdout
    assert s["start_s"] > 0
    # where the misses and the tail were: every frame that missed a head named by its tick and camera
    assert len(s["missed_frames"]) == min(100, s["frames_not_all_heads"])
    assert all(0 <= k <= s["frames_submitted"] // 2 and c in ("cam0", "cam1") for k, c in s["missed_frames"])
    slowest = s["slowest_ticks_ms"]
    assert 0 < len(slowest) <= 10 and [ms for _, ms in slowest] == sorted((ms for _, ms in slowest), reverse=True)
    assert slowest[0][1] >= s["latency_all_heads_ms"]["p99"] and "missed a head at ticks" in p.stdout
    assert [t["cameras"] for t in res["throughput"]] == [1, 2]
    assert all(t["batched_fps"] > 0 and t["separate_fps"] > 0 for t in res["throughput"])
    assert all(t["in_flight"] == 3 for t in res["throughput"])  # a file run's (Note [Frames in flight])
    assert all(set(t["frames_missing_a_head"]) == {"batched", "separate"} for t in res["throughput"])
    for t in res["throughput"]:  # where a frame's time went, for each: its results coming, and their reading
        for ms in t["frame_ms"].values():
            assert 0 < ms["ready"]["p50"] <= ms["ready"]["p99"] and 0 <= ms["read"]["p50"] <= ms["read"]["p99"]
            assert ms["ready"]["p50"] < 5_000  # ms: a tiny model's frame on the CPU is nowhere near 5 s
    for t in res["throughput"]:  # the batched engine's counts over the timed frames: every frame of every camera ran
        counted = t["batched_engine_counted"]
        assert set(counted) == {"foundation", "depth", "seg"}
        assert counted["foundation"]["runs"] >= 3 * t["cameras"] and counted["foundation"]["skipped"] == 0, counted
    bad = cli("bench", "cameras", "-c", "tiny", "--set", "device=cpu", "--heads", "nope", "--out", str(tmp_path))
    assert bad.returncode != 0 and "--heads 'nope': the config's heads are depth, seg, det" in bad.stderr


def test_heads_bench_adds_and_removes_a_head_under_a_stream_and_counts_what_is_left(tmp_path, cli):
    p = vpengine(
        "bench", "heads", "-c", "tiny", "--set", "device=cpu", "--cycles", "2", "--hold", "0.5",
        "--out", str(tmp_path), "--name", "heads", timeout=300,
    )  # fmt: skip
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    res = json.loads((tmp_path / "heads.json").read_text())
    assert res["serving"] == ["depth", "seg"] and res["added"] == "det" and len(res["cycles"]) == 2
    for c in res["cycles"]:
        assert c["add_s"] > 0 and c["runs"] > 0  # it served while attached
        assert set(c["longest_gap_ms"]) == {"depth", "seg"} and all(g > 0 for g in c["longest_gap_ms"].values())
        stops = c["interpreter"]
        assert stops["longest_stop_ms"] >= 10  # the waking thread woke, every 10 ms at best
        assert (stops["full_gcs"] > 0) == (stops["longest_full_gc_ms"] > 0)
    assert res["after"]["fds"] == res["before"]["fds"] and res["after"]["threads"] == res["before"]["threads"]
    bad = cli("bench", "heads", "-c", "tiny", "--set", "device=cpu", "--head", "nope", "--out", str(tmp_path))
    assert bad.returncode != 0 and "--head 'nope'" in bad.stderr


def test_steer_bench_measures_lanes_under_each_priority_and_a_change_through_every_door(tmp_path, cli):
    p = vpengine(
        "bench", "steer", "-c", "tiny", "--set", "device=cpu", "--set", "mode=thread", "--cameras", "2", "--seconds", "1",
        "--settle", "0.5",
        "--changes", "1", "--out", str(tmp_path), "--name", "steer", timeout=300,
    )  # fmt: skip
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    res = json.loads((tmp_path / "steer.json").read_text())
    lanes = {(h, c) for h in ("depth", "seg", "det") for c in ("cam0", "cam1")}
    for phase in ("equal", "priority"):
        rows = {(r["head"], r["camera"]): r for r in res[phase]["lanes"]}
        assert set(rows) == lanes and set(res[phase]["results_missed"]) == {"depth", "seg", "det"}
        assert rows[("depth", "cam0")]["priority"] == (0 if phase == "equal" else 10), rows[("depth", "cam0")]
        assert all(r["priority"] == 0 for lane, r in rows.items() if lane != ("depth", "cam0"))
        assert rows[("depth", "cam0")]["runs_hz"] > 0 and rows[("depth", "cam0")]["latency_ms"] is not None
        engine_side = rows[("depth", "cam0")]["engine_latency_ms"]  # every run of the phase, as the engine saw it
        assert engine_side["n"] > 0 and 0 < engine_side["p50"] <= engine_side["p99"]
        assert rows[("depth", "cam0")]["engine_latency_whole"]  # runs before the phase still kept: none lost
    # nothing is throttled while every priority is equal (Note [Give way]): every lane ran, none was capped
    assert all(r["runs_hz"] > 0 for r in res["equal"]["lanes"]), res["equal"]
    assert all(r["skipped_by"]["priority"] == 0 and r["cap_hz"] is None for r in res["equal"]["lanes"])
    assert res["change"]["lane"] == "det@cam1" and res["change"]["priority"] == 11
    assert set(res["change"]["doors"]) == {"api", "web", "ros2"}
    for door, changes in res["change"]["doors"].items():
        (c,) = changes
        assert c["priority_after"] == 11, (door, c)  # the command arrived through that door
        assert c["applied_ms"] >= 0 and c["first_run_ms"] > 0, (door, c)
    bad = cli("bench", "steer", "-c", "tiny", "--set", "device=cpu", "--doors", "api,fax", "--out", str(tmp_path))
    assert bad.returncode != 0 and "--doors: fax not known; accepted: api, web, ros2" in bad.stderr
    one = cli("bench", "steer", "-c", "tiny", "--set", "device=cpu", "--cameras", "1", "--out", str(tmp_path))
    assert one.returncode != 0 and "--cameras 1: at least 2" in one.stderr


def test_run_street_viz_runs_from_a_clone_on_the_shipped_sample_into_a_folder_of_its_own(tmp_path):
    tracked = {p: p.stat().st_mtime_ns for p in (ROOT / "benchmarks" / "results").rglob("*") if p.is_file()}
    script = ROOT / "benchmarks" / "run_street_viz.py"
    p = subprocess.run(
        [sys.executable, str(script), "--max-frames", "3"], cwd=tmp_path, capture_output=True, text=True, timeout=400
    )
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    (out,) = tmp_path.glob("run-street-viz-*")
    assert [f.name for f in out.iterdir()] == ["run_street_viz_cpu.json"]
    res = json.loads((out / "run_street_viz_cpu.json").read_text())
    assert res["summary"]["frames_submitted"] == 3 and res["summary"]["source"].endswith("street.mp4")
    assert res["command"].startswith("vpengine run --config tiny --source sample:street --out TMP/demo --viz")
    assert (
        res["printed"][0].startswith("3 frames in ")
        and 0 < res["bytes_written"] < res["bytes_written_with_depth_format_npy"]
    )
    assert f"results in {out.name}/run_street_viz_cpu.json" in p.stdout
    now = {p: p.stat().st_mtime_ns for p in (ROOT / "benchmarks" / "results").rglob("*") if p.is_file()}
    assert now == tracked


def test_resources_reports_how_long_each_engine_took_to_start(tmp_path, cli):
    # each measurement runs in a process of its own already (resources.isolated): the command around it in this one
    p = cli(
        "bench", "resources", "--config", "tiny", "--heads", "1", "--modes", "thread", "--seconds", "0.2",
        "--device", "cpu", "--height", "120", "--width", "160", "--out", str(tmp_path),
    )  # fmt: skip
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    (row,) = json.loads((tmp_path / "resources_gpu.json").read_text())["rows"]
    assert row["mode"] == "thread" and row["heads"] == 1 and 0 < row["start_s"] < 300
    assert f"started in {row['start_s']:.1f} s" in p.stdout


def test_the_pipelined_floor_refuses_more_sets_than_torchs_stream_pool_keeps_apart():
    """More sets side by side than PyTorch's pool has streams for would share streams and run one after another,
    timing a schedule that is not the one claimed: refused, naming the count, before anything runs."""
    from tests_paths import TINY
    from vpengine.bench.paper.harness import STREAM_POOL, Bench, InProcess, pipelined_ms

    b = Bench.load(TINY, ["mode=thread", "device=cpu"], frames=1)
    seq = InProcess(b, [b.head("depth", "depth"), b.head("seg", "seg")])
    sets = STREAM_POOL // 3 + 1  # three models a set
    with pytest.raises(ValueError, match=f"{sets} sets of 3 models need {3 * sets} CUDA streams side by side"):
        pipelined_ms([seq] * sets, b.images(1), 1)
