"""`vpengine bench report` on hand-made results files: every run of E2, E3, E5 and the floor gets its own row,
labelled with what ran (with a compiled backbone, detection heads still run eager, and the label says so), and nothing
is read from elsewhere."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vpengine.bench.report import FLOOR_RUNS_DRAWN, build_figure, collect, floor_panel_rows, table


def _lat(ms: float) -> dict[str, float]:
    return {"p50": ms, "p90": ms, "p99": ms, "mean": ms, "n": 10, "hz": 1e3 / ms}


def _write(folder: Path, name: str, date: str, setup: dict, **experiments: dict) -> None:
    base = {"backbone": "dinov2_vits14_dav2", "backend": "eager", "mode": "process", "mps": "off"}
    data = {"benchmark": name, "date": date, "machine": {}, "setup": {**base, **setup}, **experiments}
    (folder / f"{name}.json").write_text(json.dumps(data))


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


def test_every_e2_and_e3_run_has_a_row_labelled_with_what_ran(tmp_path):
    _write(tmp_path, "paper_cuda_e2", "2026-01-01T00:00:00", {}, E2=_e2(40.0, 60.0))
    _write(
        tmp_path,
        "paper_cuda_e2_c",
        "2026-01-02T00:00:00",
        {"backend": "compile", "mps": "required"},
        E2=_e2(20.0, 70.0),
    )
    _write(tmp_path, "paper_cuda_e3", "2026-01-01T00:00:00", {}, E3=_e3(0.96, 0.25))
    _write(tmp_path, "paper_cuda_e3_rerun", "2026-01-03T00:00:00", {}, E3=_e3(0.73, 0.30))
    r = collect(tmp_path)
    md = table(r).splitlines()

    e2 = [line for line in md if line.startswith("| E2")]
    assert len(e2) == 2, md
    assert "(dinov2_vits14_dav2, eager) | 1.50x vs sequential (engine 40.0 ms, sequential 60.0 ms" in e2[0]
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


def _floor(transfers: bool, slots: bool = False, chained: bool = False) -> dict:
    out = {
        "device_ms": {"foundation": 1.0, "depth": 0.5, "seg": 0.5},
        "floor_sum_ms": 2.0,
        "thread": _lat(3.0),
        "process": _lat(2.5),
        "thread_overhead_vs_floor": 0.5,
        "process_overhead_vs_floor": 0.25,
    }
    if transfers:
        out.update(
            transfer_ms={"upload": 0.2, "download": 0.3},
            floor_with_transfers_ms=2.5,
            thread_overhead_vs_floor_with_transfers=0.2,
            process_overhead_vs_floor_with_transfers=0.0,
        )
    if slots:
        out.update(
            thread_frame_slot=_lat(2.25),
            process_frame_slot=_lat(2.0),
            thread_frame_slot_overhead_vs_floor=0.125,
            process_frame_slot_overhead_vs_floor=0.0,
            thread_frame_slot_overhead_vs_floor_with_transfers=-0.1,
            process_frame_slot_overhead_vs_floor_with_transfers=-0.2,
        )
    if chained:
        out["chained_ms"] = {"compute": 1.8, "with_transfers": 2.3}
    return out


def test_floor_rows_add_the_transfers_where_they_were_measured(tmp_path):
    _write(
        tmp_path, "paper_cuda_floor_old", "2026-01-01T00:00:00", {"backend": "compile"}, floor=_floor(False)
    )
    _write(
        tmp_path, "paper_cuda_floor_new", "2026-01-02T00:00:00", {"backend": "compile"}, floor=_floor(True)
    )
    _write(
        tmp_path,
        "paper_cuda_floor_slot",
        "2026-01-03T00:00:00",
        {"backend": "compile"},
        floor=_floor(True, True),
    )
    rows = [line for line in table(collect(tmp_path)).splitlines() if "device-time floor" in line]
    assert len(rows) == 3, rows
    assert "frame_slot" not in rows[0] + rows[1]
    assert (
        "; frames written in place (frame_slot): thread mode 2.2 ms (+12%, -10% with transfers), "
        "process mode 2.0 ms (+0%, -20% with transfers) |" in rows[2]
    )
    assert "floor 2.0 ms; thread mode 3.0 ms (+50%), process mode 2.5 ms (+25%) |" in rows[0]
    assert "transfers" not in rows[0]
    assert (
        "with the frame's upload and the results' download 2.5 ms: thread mode +20%, process mode +0% |"
        in rows[1]
    )


def test_floor_rows_say_when_thread_mode_handed_features_or_frames_over_the_older_way_or_seg_upsampled_so(
    tmp_path,
):
    for name, date, runtime in (
        ("auto", "2026-01-01", {"feature_handoff": "event", "inline_launch": "auto"}),
        ("worker", "2026-01-02", {"feature_handoff": "event", "inline_launch": "never"}),
        ("host", "2026-01-03", {"feature_handoff": "host", "inline_launch": "never"}),
        ("prio", "2026-01-04", {"stream_priorities": {"depth": -1}}),
        ("torch", "2026-01-05", {"seg_upsample": "torch"}),
    ):
        setup = {"backend": "compile", **runtime}
        _write(tmp_path, f"paper_cuda_floor_{name}", f"{date}T00:00:00", setup, floor=_floor(True))
    rows = [line for line in table(collect(tmp_path)).splitlines() if "device-time floor" in line]
    assert len(rows) == 5, rows
    assert "(dinov2_vits14_dav2, compile; " in rows[0]
    assert "(dinov2_vits14_dav2, compile, worker launch; " in rows[1]
    assert "(dinov2_vits14_dav2, compile, host hand-off, worker launch; " in rows[2]
    assert "(dinov2_vits14_dav2, compile, stream priorities depth -1; " in rows[3]
    assert "(dinov2_vits14_dav2, compile, seg upsample torch; " in rows[4]


def test_floor_rows_give_the_chained_floor_where_it_was_measured(tmp_path):
    _write(
        tmp_path,
        "paper_cuda_floor_a",
        "2026-01-01T00:00:00",
        {"backend": "compile"},
        floor=_floor(True, True),
    )
    floor = _floor(True, True, chained=True)
    _write(tmp_path, "paper_cuda_floor_b", "2026-01-02T00:00:00", {"backend": "compile"}, floor=floor)
    rows = [line for line in table(collect(tmp_path)).splitlines() if "device-time floor" in line]
    assert len(rows) == 2 and "back to back" not in rows[0], rows
    p50 = floor["thread_frame_slot"]["p50"]
    assert (
        f"; the models back to back on one stream 1.8 ms: thread mode from a frame slot p50 {p50:.1f} ms "
        f"({p50 / 1.8 - 1:+.0%}) |" in rows[1]
    ), rows[1]


def _e5(frames: int, p50: float, lost: float) -> dict:
    return {
        "frames": frames,
        "all_three_latency_ms": _lat(p50),
        "per_head_latency_ms": {"depth": _lat(p50 / 2), "det": _lat(p50)},
        "loss_pct": {"depth": 0.0, "det": lost},
        "memory": [],
        "memory_flat": True,
    }


def test_every_e5_run_gets_a_row_and_the_figure_shows_the_longest(tmp_path):
    _write(tmp_path, "paper_cuda_e5", "2026-01-01T00:00:00", {"backend": "compile"}, E5=_e5(10000, 12.9, 0.0))
    _write(
        tmp_path,
        "paper_cuda_e5_ab",
        "2026-01-02T00:00:00",
        {"backend": "compile", "slot_bound": False},
        E5=_e5(3000, 15.0, 0.1),
    )
    r = collect(tmp_path)
    rows = [line for line in table(r).splitlines() if line.startswith("| E5")]
    assert len(rows) == 2, rows
    assert "E5 10000 frames" in rows[0] and "p50 12.9 ms" in rows[0] and "not slot-bound" not in rows[0]
    assert "E5 3000 frames" in rows[1] and "not slot-bound" in rows[1] and "lost 0.10%" in rows[1]
    assert r["E5"]["file"] == "paper_cuda_e5.json"  # the longest stream, not the newest


def test_the_wait_spin_is_in_a_label_only_where_it_ran_on_cuda(tmp_path):
    runs = [
        ("paper_cuda_floor_a", "cuda", 200.0),
        ("paper_cuda_floor_b", "cuda", 0.0),
        ("paper_cpu_floor", "cpu", 200.0),
    ]
    for day, (name, device, spin) in enumerate(runs, 1):
        setup = {"device": device, "wait_spin_us": spin}
        _write(tmp_path, name, f"2026-01-0{day}T00:00:00", setup, floor=_floor(True))
    rows = [line for line in table(collect(tmp_path)).splitlines() if "device-time floor" in line]
    assert ["wait spin 200 us" in row for row in rows] == [True, False, False]


def test_the_floor_panel_shows_the_newest_runs_that_timed_frames_written_in_place(tmp_path):
    _write(tmp_path, "paper_cuda_floor_old", "2026-01-01T00:00:00", {}, floor=_floor(True))  # no frame slot
    _write(tmp_path, "paper_cuda_floor_x", "2026-01-02T00:00:00", {}, floor=_floor(True, True))
    _write(tmp_path, "paper_cuda_floor_y", "2026-01-03T00:00:00", {}, floor=_floor(False, True))
    assert floor_panel_rows(collect(tmp_path)) == [("x", 2.0, 2.5, 2.25), ("y", 2.0, None, 2.25)]
    for i in range(FLOOR_RUNS_DRAWN + 2):
        _write(
            tmp_path,
            f"paper_cuda_floor_z{i:02}",
            f"2026-02-{i + 1:02}T00:00:00",
            {},
            floor=_floor(True, True),
        )
    rows = floor_panel_rows(collect(tmp_path))
    assert [x[0] for x in rows] == [
        f"z{i:02}" for i in range(2, FLOOR_RUNS_DRAWN + 2)
    ]  # the newest, oldest first


def test_the_figure_has_a_panel_for_each_experiment_the_folder_has_and_no_empty_ones(tmp_path):
    empty = build_figure(collect(tmp_path))
    assert empty.axes == [] and "no results in this folder" in [t.get_text() for t in empty.texts]
    e5 = _e5(10000, 12.9, 0.0)
    e5["memory"] = [{"t": float(t), "device_used": 1 << 30} for t in range(5)]
    _write(tmp_path, "paper_cuda_e5", "2026-01-01T00:00:00", {}, E5=e5)
    _write(tmp_path, "paper_cuda_floor_x", "2026-01-02T00:00:00", {}, floor=_floor(True, True))
    fig = build_figure(collect(tmp_path))
    titles = [ax.get_title() for ax in fig.axes]
    assert titles == [
        "E5: 10000 frames at 30 Hz",
        "E5: device memory over the stream",
        "engine vs device-time floor (newest runs)",
    ]
    # the transfers alone (2.5 ms against 2.0 ms summed: +25%), then the engine (2.25 ms: +12.5%)
    assert [p.get_width() for p in fig.axes[2].patches] == [pytest.approx(25.0), pytest.approx(12.5)]


EVENT_STAGES = {  # one profile_steps.py variant: mean ms after the frame is in its slot
    "foundation.input_published": 0.0,
    "caller.submitted": 0.04,
    "foundation.pinned": 0.13,
    "foundation.model_enqueued": 0.34,
    "depth.input_published": 0.38,
    "seg.input_published": 0.38,
    "depth.pinned": 0.5,
    "seg.pinned": 0.5,
    "seg.model_enqueued": 0.82,
    "depth.model_enqueued": 0.84,
    "foundation.device_done": 1.66,
    "foundation.published": 1.67,
    "seg.device_done": 2.61,
    "seg.published": 2.66,
    "depth.device_done": 3.34,
    "depth.published": 3.39,
    "caller.returned": 3.58,
}


def test_waterfall_rows_follow_the_stages_and_mark_what_each_model_published_when():
    from vpengine.bench.report import waterfall_rows

    rows = {name: (segs, out) for name, segs, out in waterfall_rows(EVENT_STAGES)}
    names = list(rows)  # in the order they start; the caller last
    assert names[0] == "foundation" and names[-1] == "caller" and set(names[1:3]) == {"depth", "seg"}
    segs, out = rows["foundation"]
    # woken 0 -> 0.13, queueing 0.13 -> 0.34, device 0.34 -> 1.66, publishing 1.66 -> 1.67
    assert [(round(s, 2), round(length, 2), i) for s, length, i in segs] == [
        (0.0, 0.13, 0),
        (0.13, 0.21, 1),
        (0.34, 1.32, 2),
        (1.66, 0.01, 3),
    ]
    assert (
        out == 0.38
    )  # the heads saw the features at 0.38 ms (event hand-off), not when the foundation finished
    assert rows["depth"][1] == 3.39
    caller_segs, returned = rows["caller"]
    assert returned == 3.58 and caller_segs[-1][0] == 3.39 and round(caller_segs[-1][1], 2) == 0.19


def test_waterfall_draws_each_variant_a_profile_has_and_nothing_for_none(tmp_path):
    from vpengine.bench.report import waterfall

    profile = {
        "setup": {"heads": ["depth", "seg"], "backend": "compile"},
        "slot": {"mean_ms": 3.58, "stages_ms_from_start": EVENT_STAGES},
        "slot host hand-off": {"mean_ms": 4.08, "stages_ms_from_start": EVENT_STAGES},
    }
    png = tmp_path / "w.png"
    assert waterfall(profile, png) and png.stat().st_size > 10_000
    assert not waterfall({"setup": {}, "submit": profile["slot"]}, tmp_path / "none.png")
    assert not (tmp_path / "none.png").exists()
