"""Turn a folder of benchmark results (JSON) into one figure and one markdown table, for the README.

    vpengine bench report --results benchmarks/results/h100

Every number it prints is read from a results file in that folder; nothing is typed in by hand.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--results", default="benchmarks/results/h100", help="folder of results files")
    p.set_defaults(out=None)


def _load(folder: Path, name: str) -> dict[str, Any] | None:
    path = folder / name
    return json.loads(path.read_text()) if path.exists() else None


def _paper_files(folder: Path) -> list[tuple[str, dict[str, Any]]]:
    """Every paper results file in ``folder`` (name, contents), each read once."""
    return [(p.name, json.loads(p.read_text())) for p in sorted(folder.glob("paper_*.json"))]


def _runs(files: list[tuple[str, dict[str, Any]]], key: str) -> list[dict[str, Any]]:
    """Every run of experiment ``key``, oldest first, each with its file name, setup, date and machine.

    Repeated runs of one setup all stay: the spread between runs is part of the result.
    """
    runs = [
        {
            "file": name,
            **data[key],
            "setup": data.get("setup", {}),
            "date": data.get("date", ""),
            "machine": data.get("machine", {}),
        }
        for name, data in files
        if key in data
    ]
    return sorted(runs, key=lambda x: (x["date"], x["file"]))


def _setup_label(setup: dict[str, Any], det: bool = False) -> str:
    label = f"{setup.get('backbone', '?')}, {setup.get('backend', '?')}"
    if det and setup.get("backend", "eager") != "eager":  # Setup.head keeps Faster R-CNN eager
        label += ", detection heads eager"
    size = (setup.get("height", 1080), setup.get("width", 1920))
    if not setup.get("tiny") and size != (1080, 1920):  # 1080p frames unless said
        label += f", {size[0]}x{size[1]}"
    if setup.get("mode", "process") != "process":
        label += f", {setup['mode']} mode"
    if setup.get("mps", "off") != "off":
        label += ", MPS"
    if setup.get("results", "copy") == "borrow":
        label += ", borrowed results"
    if setup.get("slot_bound") is False:
        label += ", not slot-bound"
    if setup.get("sync_spin_us"):
        label += f", sync spin {setup['sync_spin_us']:g} us"
    if setup.get("wait_spin_us") and str(setup.get("device", "")).startswith(
        "cuda"
    ):  # the CPU: nothing to spin for
        label += f", wait spin {setup['wait_spin_us']:g} us"
    # thread mode's features waited for on the host (runs before Note [Event hand-off] have no such key and
    # handed off on the host too)
    if setup.get("feature_handoff") == "host":
        label += ", host hand-off"
    # thread mode's results waited for by the heads on the host (as in runs before Note [Result hand-off], unlabelled)
    if setup.get("result_handoff") == "host":
        label += ", results handed off on the host"
    # thread mode's foundation launched by its worker, never by submit (so were runs before Note [Inline launch])
    if setup.get("inline_launch") == "never":
        label += ", worker launch"
    stream_priorities = setup.get("stream_priorities")
    if stream_priorities:
        label += ", stream priorities " + " ".join(f"{k} {v}" for k, v in stream_priorities.items())
    # the linear seg head's upsampling chosen for a comparison (runs before the fused kernel have no such key)
    if setup.get("seg_upsample", "auto") != "auto":
        label += f", seg upsample {setup['seg_upsample']}"
    return label


def collect(folder: Path) -> dict[str, Any]:
    out: dict[str, Any] = {}
    files = _paper_files(folder)
    for key in ("E1", "E2", "E3", "E4", "E5", "floor"):
        runs = _runs(files, key)
        if runs:
            out[key] = runs[-1]  # the newest
        # E1, E2, E3, E5 and the floor are run for several backbones, backends and modes: every run gets a row.
        if key in ("E1", "E2", "E3", "E5", "floor"):
            out[f"{key}_all"] = runs
    for key in ("E1", "E2"):  # the figure shows the run with the most head counts
        if out[f"{key}_all"]:
            out[key] = max(out[f"{key}_all"], key=lambda x: (len(x["rows"]), x["date"]))
    if out["E5_all"]:  # ... and the longest stream
        out["E5"] = max(out["E5_all"], key=lambda x: (x["frames"], x["date"]))
    for name in ("resources_gpu.json", "resources_gpu_mps-required.json", "hop_cuda_vits-1080p.json"):
        data = _load(folder, name)
        if data:
            out[name] = data
    return out


def table(r: dict[str, Any]) -> str:
    rows = ["| experiment | result | paper | file |", "| --- | --- | --- | --- |"]
    for e1 in r.get("E1_all", []):
        last = e1["rows"][-1]
        rows.append(
            f"| E1 shared backbone + {last['heads']} depth heads ({_setup_label(e1['setup'])}) | "
            f"{last['speedup_vs_independent']:.2f}x vs independent models (ideal from device times "
            f"{last.get('ideal_vs_independent', float('nan')):.2f}x), {last['speedup_vs_sequential']:.2f}x vs "
            f"sequential | 2.3x vs independent | {e1['file']} |"
        )
    for e2 in r.get("E2_all", []):
        last = e2["rows"][-1]
        dt = last["device_ms"]
        floor = f", summed device time {sum(dt.values()):.1f} ms" if dt else ""
        rows.append(
            f"| E2 {last['heads']} detection heads ({_setup_label(e2['setup'], det=True)}) | "
            f"{last['speedup_vs_sequential']:.2f}x vs sequential (engine {last['engine']['mean']:.1f} ms, sequential "
            f"{last['sequential']['mean']:.1f} ms{floor}) | 3.3x | {e2['file']} |"
        )
    for e3 in r.get("E3_all", []):
        g = {(x["head"], x["heads"]): x["throughput_gain"] for x in e3["rows"]}
        det = ", ".join(f"{n} heads {g[('det', n)]:+.0%}" for n in (4, 8) if ("det", n) in g)
        dep = ", ".join(f"{n} heads {g[('depth', n)]:+.0%}" for n in (4, 8) if ("depth", n) in g)
        rows.append(
            f"| E3 CUDA MPS on vs off ({_setup_label(e3['setup'], det=True)}) | detection: {det}; depth: {dep} | "
            f"+39% (4), +77% (8) | {e3['file']} |"
        )
    if "E4" in r:
        errs = ", ".join(f"{x['rate_hz']} Hz {x['error']:+.0f}" for x in r["E4"]["rows"])
        rows.append(
            f"| E4 rate limits, 10 s of 30 Hz input | runs vs ideal: {errs} | +-1 | {r['E4']['file']} |"
        )
    for e in r.get("E5_all", []):
        a = e["all_three_latency_ms"]
        lost = max(e["loss_pct"].values())
        rows.append(
            f"| E5 {e['frames']} frames at 30 Hz, depth+seg+det ({_setup_label(e['setup'], det=True)}) | submit -> all three on host: p50 {a['p50']:.1f} ms, "
            f"p99 {a['p99']:.1f} ms; lost {lost:.2f}%; memory flat: {e['memory_flat']} | ~0.02% lost | {e['file']} |"
        )
    for f in r.get("floor_all", []):
        if "floor_sum_ms" not in f:
            continue
        heads = "+".join(k for k in f["device_ms"] if k != "foundation")
        with_xfer = ""
        if f.get("transfer_ms"):  # runs before the transfers were measured have only the compute floor
            with_xfer = (
                f"; with the frame's upload and the results' download {f['floor_with_transfers_ms']:.1f} ms: "
                f"thread mode {f['thread_overhead_vs_floor_with_transfers']:+.0%}, process mode "
                f"{f['process_overhead_vs_floor_with_transfers']:+.0%}"
            )
        slot = ""
        if "thread_frame_slot" in f:  # runs since Engine.frame_slot also time frames written in place
            parts = []
            for m in ("thread", "process"):
                k = f"{m}_frame_slot"
                part = f"{m} mode {f[k]['mean']:.1f} ms ({f[f'{k}_overhead_vs_floor']:+.0%}"
                if f.get("transfer_ms"):
                    part += f", {f[f'{k}_overhead_vs_floor_with_transfers']:+.0%} with transfers"
                parts.append(part + ")")
            slot = "; frames written in place (frame_slot): " + ", ".join(parts)
            chained = f.get("chained_ms", {}).get("compute")
            if chained:  # runs since the chained floor: medians against a median
                p50 = f["thread_frame_slot"]["p50"]
                slot += (
                    f"; the models back to back on one stream {chained:.1f} ms: thread mode from a frame slot p50 "
                    f"{p50:.1f} ms ({p50 / chained - 1:+.0%})"
                )
        rows.append(
            f"| engine vs device-time floor ({_setup_label(f['setup'], det='det' in heads)}; {heads}) | floor {f['floor_sum_ms']:.1f} ms; "
            "thread mode "
            f"{f['thread']['mean']:.1f} ms ({f['thread_overhead_vs_floor']:+.0%}), process mode "
            f"{f['process']['mean']:.1f} ms ({f['process_overhead_vs_floor']:+.0%}){with_xfer}{slot} | - | {f['file']} |"
        )
    res = r.get("resources_gpu.json")
    if res:
        s = res["summary"]
        cpu = {x["mode"]: x for x in res["rows"] if "cpu_30hz_pct" in x}
        rows.append(
            "| E6 device memory per extra head (DINOv2-S + DA-V2 depth, 1080p, fp16) | process mode "
            f"+{s['process']['mb_per_extra_head']:.0f} MB, thread mode +{s['thread']['mb_per_extra_head']:.0f} MB "
            "| +214-295 MB | resources_gpu.json |"
        )
        rows.append(
            f"| E6 CPU, {max(x['heads'] for x in cpu.values())} heads | idle {cpu['process']['cpu_idle_pct']:.1f}% / "
            f"{cpu['thread']['cpu_idle_pct']:.1f}%, at 30 Hz {cpu['process']['cpu_30hz_pct']:.0f}% / "
            f"{cpu['thread']['cpu_30hz_pct']:.0f}% of one core (process / thread mode) | 440-465% | resources_gpu.json |"
        )
    hop = r.get("hop_cuda_vits-1080p.json")
    if hop:
        rows.append(
            f"| mailbox hop backbone -> head process, ViT-S features of a 1080p frame on the GPU | median "
            f"{hop['median_us']:.1f} us, p99 {hop['p99_us']:.1f} us | ~2 ms | hop_cuda_vits-1080p.json |"
        )
    return "\n".join(rows)


def _e1(ax: Any, r: dict[str, Any]) -> None:
    rows = r["E1"]["rows"]
    ns = [x["heads"] for x in rows]
    for s, style in (("engine", "o-"), ("independent", "s--"), ("sequential", "^:")):
        ax.plot(ns, [x[s]["hz"] for x in rows], style, label=s)
    ax.set(
        xlabel="depth heads",
        ylabel="frames/s, one frame in flight",
        title=f"E1: shared backbone vs not\n({_setup_label(r['E1'].get('setup', {}))})",
    )
    ax.legend()


def _e2(ax: Any, r: dict[str, Any]) -> None:
    rows = r["E2"]["rows"]
    ns = [x["heads"] for x in rows]
    for s, style in (("engine", "o-"), ("sequential", "^:")):
        ax.plot(ns, [x[s]["hz"] for x in rows], style, label=s)
    ax.set(
        xlabel="detection heads",
        ylabel="frames/s",
        title=f"E2: parallel vs sequential heads\n({_setup_label(r['E2'].get('setup', {}), det=True)})",
    )
    ax.legend()


def _e3(ax: Any, r: dict[str, Any]) -> None:
    rows = r["E3"]["rows"]
    labels = [f"{x['head']} x{x['heads']}" for x in rows]
    x = np.arange(len(labels))
    ax.bar(x - 0.2, [y["mps_off"]["hz"] for y in rows], 0.4, label="MPS off")
    ax.bar(x + 0.2, [y["mps_on"]["hz"] for y in rows], 0.4, label="MPS on")
    ax.set_xticks(x, labels)
    ax.set(ylabel="frames/s", title=f"E3: CUDA MPS\n({_setup_label(r['E3'].get('setup', {}), det=True)})")
    ax.legend()


def _e4(ax: Any, r: dict[str, Any]) -> None:
    rows = r["E4"]["rows"]
    rates = [x["rate_hz"] for x in rows]
    ax.plot(rates, [x["ideal"] for x in rows], "k--", label="ideal")
    ax.plot(rates, [x["runs"] for x in rows], "o", label="measured")
    ax.set(xlabel="rate limit (Hz)", ylabel="runs in 10 s", title="E4: rate limits (30 Hz input)")
    ax.legend()


def _e5_latency(ax: Any, r: dict[str, Any]) -> None:
    lat = r["E5"]["per_head_latency_ms"]
    names = list(lat)
    ax.bar(np.arange(len(names)) - 0.2, [lat[n]["p50"] for n in names], 0.4, label="p50")
    ax.bar(np.arange(len(names)) + 0.2, [lat[n]["p99"] for n in names], 0.4, label="p99")
    ax.set_xticks(np.arange(len(names)), names)
    ax.set(ylabel="submit -> result (ms)", title=f"E5: {r['E5']['frames']} frames at 30 Hz")
    ax.axhline(33.3, color="grey", lw=0.8, ls=":")
    ax.legend()


def _e5_memory(ax: Any, r: dict[str, Any]) -> None:
    mem = r["E5"]["memory"]
    base = mem[0]["device_used"]
    ax.plot([m["t"] for m in mem], [(m["device_used"] - base) / 2**20 for m in mem])
    ax.set(xlabel="seconds", ylabel="device memory change (MiB)", title="E5: device memory over the stream")
    ax.set_ylim(-8, 8)
    ax.ticklabel_format(useOffset=False)


#: floor runs drawn, newest last
FLOOR_RUNS_DRAWN = 8


def floor_panel_rows(r: dict[str, Any]) -> list[tuple[str, float, float | None, float]]:
    """The floor panel's runs, newest last: (file name less ``paper_cuda_floor_`` and ``.json``, summed device
    time, the same with the frame's upload and the results' download or None, the engine's thread-mode mean from a
    frame slot, as the table's percentages), in ms; only runs that timed frames written in place."""
    rows = []
    for f in r.get("floor_all", []):
        if "floor_sum_ms" not in f or "thread_frame_slot" not in f:
            continue
        name = f["file"].removeprefix("paper_cuda_floor_").removesuffix(".json")
        rows.append(
            (name, f["floor_sum_ms"], f.get("floor_with_transfers_ms"), f["thread_frame_slot"]["p50"])
        )
    return rows[-FLOOR_RUNS_DRAWN:]


def _floor(ax: Any, r: dict[str, Any]) -> None:
    rows = floor_panel_rows(r)
    y = np.arange(len(rows))
    over = [100 * (x[3] / x[1] - 1) for x in rows]
    xfer = [100 * (x[2] / x[1] - 1) if x[2] else 0.0 for x in rows]
    ax.barh(y - 0.2, xfer, 0.4, color="#bbbbbb", label="the frame's upload and the results' download alone")
    ax.barh(y + 0.2, over, 0.4, color="#4a7fc0", label="engine, thread mode, frame written in place (mean)")
    for yi, v in zip(y, over):
        ax.text(v, yi + 0.2, f" {v:+.0f}%", va="center", fontsize=7)
    ax.axvline(20, color="#c04040", lw=1, ls="--", label="target: +20%")
    ax.set_yticks(y, [x[0] for x in rows], fontsize=7)
    ax.invert_yaxis()
    ax.set(xlabel="% over the models' summed device time", title="engine vs device-time floor (newest runs)")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=1, frameon=False)


def _panels(r: dict[str, Any]) -> list[Any]:
    """The figure's panels that ``r`` has data for, in order."""
    mem = r.get("E5", {}).get("memory")
    have = {
        _e1: "E1" in r,
        _e2: "E2" in r,
        _e3: "E3" in r,
        _e4: "E4" in r,
        _e5_latency: "E5" in r,
        _e5_memory: bool(mem) and mem[0]["device_used"] is not None,
        _floor: bool(floor_panel_rows(r)),
    }
    return [draw for draw, present in have.items() if present]


def build_figure(r: dict[str, Any]) -> Any:
    """One panel per experiment the folder has results for, three to a row (none: a figure saying so)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = _panels(r)
    cols = min(3, max(1, len(panels)))
    rows = max(1, -(-len(panels) // cols))
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 4 * rows), dpi=110, squeeze=False)
    flat = list(axes.flat)
    for draw, ax in zip(panels, flat):
        draw(ax, r)
    for ax in flat[len(panels) :]:
        fig.delaxes(ax)
    if not panels:
        fig.text(0.5, 0.5, "no results in this folder", ha="center", va="center")
    newest = r.get("E5") or r.get("E1") or r.get("floor") or {}
    fig.suptitle(f"vpengine on {newest.get('machine', {}).get('gpu', '?')}")
    fig.tight_layout()
    return fig


def figure(r: dict[str, Any], path: Path) -> None:
    import matplotlib.pyplot as plt

    fig = build_figure(r)
    fig.savefig(path)
    plt.close(fig)


# profile_steps.py variants drawn, in this order, where a file has them
WATERFALL_VARIANTS = ("slot host hand-off", "slot worker launch", "slot", "slot+spin200")
_SEGMENTS = (  # (from stage, to stage, what the time is, colour)
    ("input_published", "pinned", "woken (a model by its input, the caller by results)", "#bbbbbb"),
    ("pinned", "model_enqueued", "host work: queueing device work (the caller: submit)", "#f0a030"),
    ("model_enqueued", "device_done", "device work, until its thread sees it done", "#4a7fc0"),
    ("device_done", "published", "counting and publishing", "#50a050"),
)


def waterfall_rows(
    stages: dict[str, float],
) -> list[tuple[str, list[tuple[float, float, int]], float | None]]:
    """Per model (in the order they start): its segments (start ms, length ms, index into _SEGMENTS) and when its
    output was published for its readers, from one variant's mean stage times of profile_steps.py."""
    per: dict[str, dict[str, float]] = {}
    for key, t in stages.items():
        model, _, stage = key.partition(".")
        per.setdefault(model, {})[stage] = t
    caller = per.pop("caller", {})
    # what the heads saw published: with the event hand-off that is before the foundation's work is done
    heads_input = [
        m["input_published"] for n, m in per.items() if n != "foundation" and "input_published" in m
    ]
    rows = []
    for name, m in sorted(per.items(), key=lambda kv: kv[1].get("pinned", 0.0)):
        segs = [
            (m[a], m[b] - m[a], i)
            for i, (a, b, _, _) in enumerate(_SEGMENTS)
            if a in m and b in m and m[b] >= m[a]
        ]
        out = min(heads_input) if name == "foundation" and heads_input else m.get("published")
        rows.append((name, segs, out))
    if caller:
        last = max((m.get("published", 0.0) for m in per.values()), default=0.0)
        segs = [(0.0, caller.get("submitted", 0.0), 1)]
        if "returned" in caller and caller["returned"] >= last:
            segs.append((last, caller["returned"] - last, 0))
        rows.append(("caller", segs, caller.get("returned")))
    return rows


def waterfall(profile: dict[str, Any], path: Path) -> bool:
    """One frame's time, stage by stage, for each variant of a profile_steps.py result; False: nothing to draw."""
    variants = [v for v in WATERFALL_VARIANTS if v in profile]
    if not variants:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    height = 1.0 + 1.9 * len(variants)
    fig, axes = plt.subplots(len(variants), 1, figsize=(11, height), dpi=110, sharex=True)
    axes = np.atleast_1d(axes)
    for ax, v in zip(axes, variants, strict=True):
        rows = waterfall_rows(profile[v]["stages_ms_from_start"])
        for y, (_name, segs, out) in enumerate(rows):
            for start, length, i in segs:
                ax.barh(y, length, left=start, color=_SEGMENTS[i][3], height=0.6)
            if out is not None:
                ax.plot([out], [y], "k|", markersize=14)
        ax.set_yticks(range(len(rows)), [r[0] for r in rows])
        ax.invert_yaxis()
        ax.set_title(
            f"{v}: {profile[v]['mean_ms']:.2f} ms mean from the frame in its slot to the caller holding results"
        )
        ax.grid(axis="x", alpha=0.3)
    axes[-1].set_xlabel("ms after the frame is in its input slot (mean over frames); | = output published")
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for _, _, _, c in _SEGMENTS]
    fig.legend(handles, [s[2] for s in _SEGMENTS], loc="lower center", ncol=2, frameon=False)
    setup = profile.get("setup", {})
    fig.suptitle(
        f"Where one frame's time goes, thread mode ({', '.join(setup.get('heads', []))}, {setup.get('backend', '?')})"
    )
    # room for the legend's two rows below the axis label, whatever the height
    fig.tight_layout(rect=(0, 0.7 / height, 1, 1))
    fig.savefig(path)
    plt.close(fig)
    return True


def main(args: argparse.Namespace) -> int:
    folder = Path(args.results)
    r = collect(folder)
    md = table(r)
    (folder / "summary.md").write_text(md + "\n")
    figure(r, folder / "summary.png")
    print(md)
    print(f"-> {folder / 'summary.md'}, {folder / 'summary.png'}")
    for f in sorted(folder.glob("profile_steps*.json")):
        png = f.with_name(f"waterfall_{f.stem.removeprefix('profile_steps').strip('_') or 'run'}.png")
        if waterfall(json.loads(f.read_text()), png):
            print(f"-> {png}")
    return 0
