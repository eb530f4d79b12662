"""`vpengine bench report` on hand-made results files: every run of an experiment gets its own row, labelled with what
ran (the config's backbone and backend, what differs from the usual, and any other override as given) and naming its
file; the summary names the machine; the figure has a panel for each experiment the folder holds; a baseline compares
each run with the baseline's run of the same experiment; nothing is read from elsewhere."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from vpengine.bench import report
from vpengine.bench.report import (
    FLOOR_RUNS_DRAWN,
    build_figure,
    collect,
    floor_panel_rows,
    setup_label,
    table,
)

H100 = {"gpu": "NVIDIA H100 80GB HBM3", "cpu": "Intel Xeon", "cores": 16, "torch": "2.11.0", "cuda": "13.0"}


def _lat(ms: float, p50: float | None = None) -> dict[str, float]:
    p50 = ms if p50 is None else p50
    return {"p50": p50, "p90": ms, "p99": ms, "mean": ms, "n": 10, "hz": 1e3 / ms}


def _setup(**changes: object) -> dict:
    base = {
        "backbone": "dinov2_vits14_dav2",
        "backend": "compile",
        "mode": "process",
        "mps": "off",
        "height": 1080,
        "width": 1920,
        "results": "copy",
        "overrides": [],
        "heads": {
            "depth": {"backend": "compile"},
            "seg": {"backend": "compile"},
            "det": {"backend": "eager"},
        },
    }
    return {**base, **changes}


def _write(folder: Path, name: str, date: str, setup: dict | None = None, **experiments: dict) -> None:
    data = {"benchmark": name, "date": date, "machine": H100, "setup": setup or _setup(), **experiments}
    (folder / f"{name}.json").write_text(json.dumps(data))


def _e1(n: int, engine: float, independent: float) -> dict:
    row = {
        "heads": n,
        "engine": _lat(engine),
        "independent": _lat(independent),
        "sequential": _lat(4 * engine),
        "device_ms": {"foundation": 1.0, "depth0": 0.5},
        "speedup_vs_independent": independent / engine,
        "speedup_vs_sequential": 4.0,
        "ideal_vs_independent": 2.2,
    }
    return {"rows": [row]}


def _e2(engine: float, sequential: float) -> dict:
    row = {
        "heads": 8,
        "engine": _lat(engine),
        "sequential": _lat(sequential),
        "device_ms": {"foundation": 1.0, "det0": 6.0},
        "speedup_vs_sequential": sequential / engine,
    }
    return {"rows": [row]}


def _e3(det8: float, depth8: float) -> dict:
    rows = [
        {"head": h, "heads": 8, "mps_off": _lat(20.0), "mps_on": _lat(10.0), "throughput_gain": g}
        for h, g in (("det", det8), ("depth", depth8))
    ]
    return {"rows": rows}


def test_labels_say_what_differs_from_the_usual_and_any_other_override():
    assert setup_label(_setup()) == "dinov2_vits14_dav2, compile"
    assert setup_label(_setup(), det=True) == "dinov2_vits14_dav2, compile, detection heads eager"
    odd = _setup(
        mode="thread",
        mps="required",
        results="borrow",
        height=518,
        width=518,
        overrides=["mode=thread", "mps=required", "input.height=518", "heads.seg.options.upsample=torch"],
    )
    assert setup_label(odd) == (
        "dinov2_vits14_dav2, compile, 518x518, thread mode, MPS, borrowed results, heads.seg.options.upsample=torch"
    )


def test_every_e2_and_e3_run_has_a_row_labelled_with_what_ran(tmp_path):
    _write(tmp_path, "paper_cuda_e2", "2026-01-01T00:00:00", _setup(backend="eager"), E2=_e2(40.0, 60.0))
    _write(tmp_path, "paper_cuda_e2_c", "2026-01-02T00:00:00", _setup(mps="required"), E2=_e2(20.0, 70.0))
    _write(tmp_path, "paper_cuda_e3", "2026-01-01T00:00:00", E3=_e3(0.96, 0.25))
    _write(tmp_path, "paper_cuda_e3_rerun", "2026-01-03T00:00:00", E3=_e3(0.73, 0.30))
    r = collect(tmp_path)
    md = table(r).splitlines()

    e2 = [line for line in md if line.startswith("| E2")]
    assert len(e2) == 2, md
    assert "(dinov2_vits14_dav2, eager) | 1.50x vs sequential (engine 40.0 ms" in e2[0]  # det eager too: unsaid
    assert "(dinov2_vits14_dav2, compile, detection heads eager, MPS) | 3.50x" in e2[1]
    assert e2[1].endswith("| paper_cuda_e2_c.json |")

    e3 = [line for line in md if line.startswith("| E3")]
    assert len(e3) == 2, md
    assert "detection: 8 heads +96%; depth: 8 heads +25%" in e3[0] and "paper_cuda_e3.json" in e3[0]
    assert "detection: 8 heads +73%; depth: 8 heads +30%" in e3[1] and "paper_cuda_e3_rerun.json" in e3[1]
    assert r["E3"]["file"] == "paper_cuda_e3_rerun.json"  # the figure shows the newest run


def test_an_empty_folder_gives_a_table_with_no_rows(tmp_path):
    md = table(collect(tmp_path)).splitlines()
    assert md == ["| experiment | result | paper | file |", "| --- | --- | --- | --- |"]


def _floor(thread_mean: float = 2.25, thread_p50: float | None = None) -> dict:
    return {
        "heads": ["depth", "seg"],
        "device_ms": {"foundation": 1.0, "depth": 0.5, "seg": 0.5},
        "transfer_ms": {"upload": 0.2, "download": 0.3},
        "chained_ms": {"compute": 1.8, "with_transfers": 2.3},
        "floor_sum_ms": 2.0,
        "floor_with_transfers_ms": 2.5,
        "thread": _lat(3.0),
        "process": _lat(2.5),
        "thread_frame_slot": _lat(thread_mean, thread_p50),
        "process_frame_slot": _lat(2.0),
        "thread_overhead_vs_floor": 0.5,
        "process_overhead_vs_floor": 0.25,
        "thread_frame_slot_overhead_vs_floor": thread_mean / 2.0 - 1,
        "process_frame_slot_overhead_vs_floor": 0.0,
    }


def test_a_floor_row_gives_the_three_floors_and_each_mode_over_the_summed_one(tmp_path):
    _write(tmp_path, "paper_cuda_floor", "2026-01-01T00:00:00", floor=_floor())
    (row,) = [line for line in table(collect(tmp_path)).splitlines() if "device-time floor" in line]
    assert row.startswith("| engine vs device-time floor (dinov2_vits14_dav2, compile; depth+seg) | ")
    assert (
        "floor 2.00 ms summed, 2.50 ms with the frame's upload and the results' download, 1.80 ms back to back on "
        "one stream; thread mode 3.00 ms submitted (+50%), 2.25 ms written in place (+12%); process mode 2.50 ms "
        "submitted (+25%), 2.00 ms written in place (+0%) | - | paper_cuda_floor.json |" in row
    )


def test_a_floor_row_gives_a_frames_share_of_each_batch_size_measured(tmp_path):
    f = _floor()
    f["by_batch"] = {
        "16": {"device_ms": {}, "chained_ms": 16.0, "chained_ms_a_frame": 1.0},
        "1": {"device_ms": {}, "chained_ms": 1.8, "chained_ms_a_frame": 1.8},
        "2": {"device_ms": {}, "chained_ms": 2.4, "chained_ms_a_frame": 1.2},
    }
    _write(tmp_path, "paper_cuda_floor", "2026-01-01T00:00:00", floor=f)
    (row,) = [line for line in table(collect(tmp_path)).splitlines() if "device-time floor" in line]
    assert (
        "1.80 ms back to back on one stream; a frame back to back in a batch of 1: 1.80 ms, 2: 1.20 ms, 16: 1.00 ms; "
        "thread mode 3.00 ms submitted" in row
    )
    assert "pipelined" not in row  # a file from before the pipelined floor


def test_a_floor_row_gives_what_batching_buys_pipelined(tmp_path):
    f = _floor()
    f["by_batch"] = {
        str(n): {
            "device_ms": {},
            "chained_ms": 1.8 * n,
            "chained_ms_a_frame": 1.8,
            "pipelined_ms": 1.5 * n,
            "pipelined_ms_a_frame": 1.5,
            "separate_pipelined_ms_a_frame": sep,
            "batching_gain": sep / 1.5,
        }
        for n, sep in ((1, 1.5), (4, 1.95))
    }
    _write(tmp_path, "paper_cuda_floor", "2026-01-01T00:00:00", floor=f)
    (row,) = [line for line in table(collect(tmp_path)).splitlines() if "device-time floor" in line]
    assert (
        "pipelined, a batch against as many engines of one frame: 4: 1.50 against 1.95 ms (batching 1.30x); "
        "thread mode" in row
    )


def test_a_floor_off_cuda_has_no_floors_and_says_so(tmp_path):
    f = {k: v for k, v in _floor().items() if "overhead" not in k and "floor_" not in k}
    f.update(device_ms={}, transfer_ms={}, chained_ms={})
    _write(tmp_path, "paper_cpu", "2026-01-01T00:00:00", _setup(backend="eager"), floor=f)
    r = collect(tmp_path)
    (row,) = [line for line in table(r).splitlines() if "device-time floor" in line]
    assert "(dinov2_vits14_dav2, eager; depth+seg) | no device times off CUDA; thread mode 3.00 ms submitted," in row
    assert floor_panel_rows(r) == []


def _e5(frames: int, p50: float, lost: float, flat: bool | None = True) -> dict:
    return {
        "frames": frames,
        "all_three_latency_ms": _lat(20.0, p50),
        "per_head_latency_ms": {"depth": _lat(p50 / 2), "det": _lat(p50)},
        "loss_pct": {"depth": 0.0, "det": lost},
        "memory": [],
        "memory_flat": flat,
    }


def test_every_e5_run_gets_a_row_and_the_figure_shows_the_longest(tmp_path):
    _write(tmp_path, "paper_cuda_e5", "2026-01-01T00:00:00", E5=_e5(10000, 12.9, 0.0))
    _write(
        tmp_path,
        "paper_cuda_e5_thread",
        "2026-01-02T00:00:00",
        _setup(mode="thread"),
        E5=_e5(3000, 15.0, 0.1),
    )
    _write(tmp_path, "paper_cpu_e5", "2026-01-03T00:00:00", E5=_e5(300, 5.0, 0.0, flat=None))
    r = collect(tmp_path)
    rows = [line for line in table(r).splitlines() if line.startswith("| E5")]
    assert len(rows) == 3, rows
    assert "E5 10000 frames" in rows[0] and "p50 12.9 ms" in rows[0] and "memory flat: True" in rows[0]
    assert "E5 3000 frames" in rows[1] and "thread mode" in rows[1] and "lost 0.10%" in rows[1]
    assert "device memory not measured" in rows[2]
    assert r["E5"]["file"] == "paper_cuda_e5.json"  # the longest stream, not the newest


def test_the_floor_panel_shows_the_newest_runs_thread_mode_means(tmp_path):
    _write(tmp_path, "paper_cuda_floor_x", "2026-01-02T00:00:00", floor=_floor(2.25, thread_p50=9.0))
    assert floor_panel_rows(collect(tmp_path)) == [("cuda_floor_x", 2.0, 2.5, 2.25)]  # the mean, not the p50
    for i in range(FLOOR_RUNS_DRAWN + 2):
        _write(tmp_path, f"paper_cuda_floor_z{i:02}", f"2026-02-{i + 1:02}T00:00:00", floor=_floor())
    rows = floor_panel_rows(collect(tmp_path))
    assert [x[0] for x in rows] == [f"cuda_floor_z{i:02}" for i in range(2, FLOOR_RUNS_DRAWN + 2)]


def test_the_figure_has_a_panel_for_each_experiment_the_folder_has_and_no_empty_ones(tmp_path):
    empty = build_figure(collect(tmp_path))
    assert empty.axes == [] and "no results in this folder" in [t.get_text() for t in empty.texts]
    e5 = _e5(10000, 12.9, 0.0)
    e5["memory"] = [{"t": float(t), "device_used": 1 << 30} for t in range(5)]
    _write(tmp_path, "paper_cuda_e5", "2026-01-01T00:00:00", E5=e5)
    _write(tmp_path, "paper_cuda_floor_x", "2026-01-02T00:00:00", floor=_floor())
    fig = build_figure(collect(tmp_path))
    titles = [ax.get_title() for ax in fig.axes]
    assert titles == [
        "E5: 10000 frames at 30 Hz",
        "E5: device memory over the stream",
        "engine vs device-time floor (newest runs)",
    ]
    # the transfers alone (2.5 ms against 2.0 ms summed: +25%), then the engine (2.25 ms: +12.5%)
    assert [p.get_width() for p in fig.axes[2].patches] == [pytest.approx(25.0), pytest.approx(12.5)]
    assert fig._suptitle.get_text() == "vpengine on NVIDIA H100 80GB HBM3"


def test_a_baseline_compares_each_run_with_the_baselines_run_of_the_same_experiment(tmp_path):
    _write(tmp_path, "paper_cuda_before_e1", "2026-01-01T00:00:00", E1=_e1(8, 10.0, 25.0))
    _write(tmp_path, "paper_cuda_after_e1", "2026-01-01T00:10:00", E1=_e1(8, 10.4, 25.0))
    _write(tmp_path, "paper_cuda_before_floor", "2026-01-01T00:20:00", floor=_floor(2.0))
    _write(tmp_path, "paper_cuda_after_floor", "2026-01-01T00:30:00", floor=_floor(2.1))
    _write(tmp_path, "paper_cuda_after_e5", "2026-01-01T00:40:00", E5=_e5(3000, 10.0, 0.0))  # no baseline run
    md = report.comparison(collect(tmp_path), "before").splitlines()
    assert md[2] == "| E1 | engine, 8 heads, mean | 10.00 | 10.40 | +4.0% | paper_cuda_after_e1.json |"
    floor = [line for line in md if line.startswith("| floor")]
    assert floor == [
        "| floor | thread mode, mean | 3.00 | 3.00 | +0.0% | paper_cuda_after_floor.json |",
        "| floor | thread mode, written in place, mean | 2.00 | 2.10 | +5.0% | paper_cuda_after_floor.json |",
        "| floor | process mode, mean | 2.50 | 2.50 | +0.0% | paper_cuda_after_floor.json |",
        "| floor | process mode, written in place, mean | 2.00 | 2.00 | +0.0% | paper_cuda_after_floor.json |",
    ]
    assert not [line for line in md if line.startswith("| E5")]


def test_main_writes_the_summary_naming_the_machine_and_the_figure(tmp_path, capsys):
    _write(tmp_path, "paper_cuda_before", "2026-01-01T00:00:00", E1=_e1(8, 10.0, 25.0))
    _write(tmp_path, "paper_cuda_after", "2026-01-02T00:00:00", E1=_e1(8, 9.0, 25.0))
    assert report.main(argparse.Namespace(results=str(tmp_path), baseline="before")) == 0
    md = (tmp_path / "summary.md").read_text()
    assert md.startswith(
        f"# vpengine benchmarks: {tmp_path.name}\n\nMachine: NVIDIA H100 80GB HBM3, 16-core Intel Xeon"
    )
    assert "torch 2.11.0, CUDA 13.0" in md
    assert "| E1 shared backbone + 8 depth heads (dinov2_vits14_dav2, compile) | engine 9.0 ms: 2.78x vs" in md
    assert "## Against the baseline (files named *before*)" in md and "| -10.0% | paper_cuda_after.json |" in md
    assert (tmp_path / "summary.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    with pytest.raises(ValueError, match="is not a folder"):
        report.main(argparse.Namespace(results=str(tmp_path / "nothing"), baseline=None))


def test_a_cameras_file_gives_its_stream_and_throughput_rows_against_the_targets(tmp_path):
    counted = {"foundation": {"skipped": 0}, "det": {"skipped": 3}}
    data = {
        "date": "2026-01-01T00:00:00",
        "machine": H100,
        "heads": ["depth", "det"],
        "stream": {
            "cameras": 4,
            "fps_per_camera": 30.0,
            "frames_submitted": 100,
            "frames_all_heads": 97,
            "latency_all_heads_ms": _lat(40.0, 20.0),
            "device_memory_bytes": 3 * 2**30,
            "counted": counted,
        },
        "throughput": [
            {"cameras": 1, "batched_fps": 70.0, "separate_fps": 70.0, "ratio": 1.0},
            {"cameras": 4, "batched_fps": 120.0, "separate_fps": 80.0, "ratio": 1.5},
        ],
    }
    (tmp_path / "cameras_cuda.json").write_text(json.dumps(data))
    rows = table(collect(tmp_path)).splitlines()[2:]
    assert rows == [
        "| 4 cameras at 30 Hz each, depth+det (thread mode) | submit -> every head: p50 20.0 ms, p99 40.0 ms; 97 of "
        "100 frames through every head (skipped, counted: det 3); device memory 3.00 GiB | target: p99 <= 33 ms, "
        "<= 2.5 GiB | cameras_cuda.json |",
        "| cameras: one engine batched vs separate engines, frames/s (depth+det) | 1: 70 vs 70 (1.00x), 4: 120 vs 80 "
        "(1.50x) | target: >= 1.5x at 4 cameras | cameras_cuda.json |",
    ]
    assert report.main(argparse.Namespace(results=str(tmp_path), baseline=None)) == 0
    assert "Machine: NVIDIA H100 80GB HBM3" in (tmp_path / "summary.md").read_text()
    assert [d.__name__ for d in report._panels(collect(tmp_path))] == ["_cameras"]


def test_a_folder_with_nothing_the_report_reads_says_what_it_reads_and_what_is_there(tmp_path, capsys):
    """bench report over a folder of another bench's files (hop_cpu.json) or of run folders wrote an empty summary
    without a word; it says so, on the terminal and in the summary."""
    import argparse

    from vpengine.bench.report import main

    (tmp_path / "hop_cpu.json").write_text("{}")
    (tmp_path / "run1").mkdir()
    (tmp_path / "run1" / "paper_cpu.json").write_text("{}")
    assert main(argparse.Namespace(results=str(tmp_path), out=str(tmp_path / "o"), baseline=None)) == 0
    err = capsys.readouterr().err
    assert err.startswith("vpengine bench report: WARNING: No results this report reads here (paper_*.json")
    assert "its JSON files: hop_cpu.json; folders with results below it: run1 (give one as --results)." in err
    assert "its JSON files: hop_cpu.json" in (tmp_path / "o" / "summary.md").read_text()
