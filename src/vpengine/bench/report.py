"""``vpengine bench report``: a folder of results files (one folder per GPU kind) -> summary.md and summary.png.

    vpengine bench report --results benchmarks/results/<GPU kind> --out benchmarks/results/<GPU kind>
    vpengine bench report --results DIR --out DIR --baseline before   # each run against files named *before*

Every number it writes is read from a results file in that folder, and every row names its file; nothing is typed in
by hand. This is the one place the paper experiments' figures are drawn.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

#: experiments of ``vpengine bench paper`` a results file may hold
PAPER = ("E1", "E2", "E3", "E4", "E5", "floor")
#: runs drawn in the floor panel, newest last
FLOOR_RUNS_DRAWN = 8


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--results", required=True, help="folder of results files, e.g. benchmarks/results/<GPU kind>")
    p.add_argument(
        "--baseline",
        metavar="NAME",
        help="compare every run with the newest run of the same experiment in a file whose name holds NAME",
    )


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


#: The files of benchmarks other than the paper's and cameras' that the report reads, by name
OTHER_FILES = ("resources_gpu.json", "resources_gpu_mps-required.json", "hop_cuda_vits-1080p.json")


def collect(folder: Path) -> dict[str, Any]:
    """``{key}_all``: every run of each experiment, oldest first; ``{key}``: the run the figure draws (the newest,
    for E1 and E2 the one with the most head counts, for E5 the longest stream); other benchmarks' files by name."""
    files = _paper_files(folder)
    out: dict[str, Any] = {}
    for key in PAPER:
        runs = out[f"{key}_all"] = _runs(files, key)
        if runs:
            out[key] = runs[-1]
    for key in ("E1", "E2"):
        if out[f"{key}_all"]:
            out[key] = max(out[f"{key}_all"], key=lambda x: (len(x["rows"]), x["date"]))
    if out["E5_all"]:
        out["E5"] = max(out["E5_all"], key=lambda x: (x["frames"], x["date"]))
    for name in OTHER_FILES:
        path = folder / name
        if path.exists():
            out[name] = json.loads(path.read_text())
    out["cameras_all"] = [{"file": p.name, **json.loads(p.read_text())} for p in sorted(folder.glob("cameras_*.json"))]
    return out


# the overrides a label already says in words
_LABELLED = {
    "mode",
    "mps",
    "device",
    "input.height",
    "input.width",
    "foundation_model.model",
    "foundation_model.backend",
}


def _cores(run: dict[str, Any]) -> str:
    """The engine's CPU over a run, where the run measured it (older results did not)."""
    cores = run.get("cpu_cores")
    return "" if cores is None else f", CPU {100 * cores:.0f}% of a core"


def setup_label(setup: dict[str, Any], det: bool = False) -> str:
    """What ran, in a few words: backbone and backend, then only what differs from the usual (1080p, process mode,
    no MPS, results copied), then any other ``--set`` override as given."""
    label = f"{setup.get('backbone', '?')}, {setup.get('backend', '?')}"
    det_backend = setup.get("heads", {}).get("det", {}).get("backend")
    if det and det_backend and det_backend != setup.get("backend"):
        label += f", detection heads {det_backend}"
    size = (setup.get("height", 1080), setup.get("width", 1920))
    if size != (1080, 1920):
        label += f", {size[0]}x{size[1]}"
    frames = setup.get("frame_size")  # [width, height] of the frames submitted, when not the canvas
    if frames and tuple(frames) != size[::-1]:
        label += f", {frames[0]}x{frames[1]} frames (boundary)"
    if setup.get("mode", "process") != "process":
        label += f", {setup['mode']} mode"
    if setup.get("mps") == "required":
        label += ", MPS"
    if setup.get("results", "copy") == "borrow":
        label += ", borrowed results"
    for o in setup.get("overrides", []):
        if o.partition("=")[0].strip() not in _LABELLED:
            label += f", {o}"
    return label


def machine_label(machine: dict[str, Any]) -> str:
    """``NVIDIA H100 80GB HBM3, 16-core Intel Xeon ..., torch 2.11.0, CUDA 13.0`` (no GPU: the CPU alone)."""
    cpu = f"{machine.get('cores', '?')}-core {machine.get('cpu', '?')}"
    parts = [machine["gpu"], cpu] if machine.get("gpu") else [cpu]
    parts.append(f"torch {machine.get('torch', '?')}")
    if machine.get("cuda"):
        parts.append(f"CUDA {machine['cuda']}")
    return ", ".join(parts)


def table(r: dict[str, Any]) -> str:
    rows = ["| experiment | result | paper | file |", "| --- | --- | --- | --- |"]
    for e1 in r.get("E1_all", []):
        last = e1["rows"][-1]
        ideal = (
            f" (ideal from device times {last['ideal_vs_independent']:.2f}x)" if "ideal_vs_independent" in last else ""
        )
        rows.append(
            f"| E1 shared backbone + {last['heads']} depth heads ({setup_label(e1['setup'])}) | "
            f"engine {last['engine']['mean']:.1f} ms{_cores(last['engine'])}: {last['speedup_vs_independent']:.2f}x "
            "vs independent models"
            f"{ideal}, {last['speedup_vs_sequential']:.2f}x vs sequential | 2.3x vs independent | {e1['file']} |"
        )
    for e2 in r.get("E2_all", []):
        last = e2["rows"][-1]
        dt = last["device_ms"]
        summed = f", summed device time {sum(dt.values()):.1f} ms" if dt else ""
        rows.append(
            f"| E2 {last['heads']} detection heads ({setup_label(e2['setup'], det=True)}) | "
            f"{last['speedup_vs_sequential']:.2f}x vs sequential (engine {last['engine']['mean']:.1f} ms, sequential "
            f"{last['sequential']['mean']:.1f} ms{summed}) | 3.3x | {e2['file']} |"
        )
    for e3 in r.get("E3_all", []):
        g = {(x["head"], x["heads"]): x["throughput_gain"] for x in e3["rows"]}
        det = ", ".join(f"{n} heads {g[('det', n)]:+.0%}" for n in (4, 8) if ("det", n) in g)
        dep = ", ".join(f"{n} heads {g[('depth', n)]:+.0%}" for n in (4, 8) if ("depth", n) in g)
        rows.append(
            f"| E3 CUDA MPS on vs off ({setup_label(e3['setup'], det=True)}) | detection: {det}; depth: {dep} | "
            f"+39% (4), +77% (8) | {e3['file']} |"
        )
    for e4 in r.get("E4_all", []):
        errs = ", ".join(f"{x['rate_hz']} Hz {x['error']:+.0f}" for x in e4["rows"])
        rows.append(
            f"| E4 rate limits, {e4['input_seconds']:.0f} s of 30 Hz input ({setup_label(e4['setup'])}) | runs vs ideal: "
            f"{errs} | +-1 | {e4['file']} |"
        )
    for e in r.get("E5_all", []):
        a = e["all_three_latency_ms"]
        rows.append(
            f"| E5 {e['frames']} frames at 30 Hz, depth+seg+det ({setup_label(e['setup'], det=True)}) | submit -> all "
            f"three on host: p50 {a['p50']:.1f} ms, p99 {a['p99']:.1f} ms; lost {max(e['loss_pct'].values()):.2f}%; "
            f"{_memory(e['memory_flat'])}{_cores(e)} | ~0.02% lost | {e['file']} |"
        )
    for f in r.get("floor_all", []):
        rows.append(_floor_row(f))
    res = r.get("resources_gpu.json")
    if res:
        s = res["summary"]
        cpu = {x["mode"]: x for x in res["rows"] if "cpu_30hz_pct" in x}
        rows.append(
            "| E6 device memory per extra head | process mode "
            f"+{s['process']['mb_per_extra_head']:.0f} MB, thread mode +{s['thread']['mb_per_extra_head']:.0f} MB "
            "| +214-295 MB | resources_gpu.json |"
        )
        rows.append(
            f"| E6 CPU, {max(x['heads'] for x in cpu.values())} heads | idle {cpu['process']['cpu_idle_pct']:.1f}% / "
            f"{cpu['thread']['cpu_idle_pct']:.1f}%, at 30 Hz {cpu['process']['cpu_30hz_pct']:.0f}% / "
            f"{cpu['thread']['cpu_30hz_pct']:.0f}% of one core (process / thread mode) | 440-465% | resources_gpu.json |"
        )
    for c in r.get("cameras_all", []):
        rows += _camera_rows(c)
    hop = r.get("hop_cuda_vits-1080p.json")
    if hop:
        rows.append(
            f"| mailbox hop backbone -> head process, ViT-S features of a 1080p frame on the GPU | median "
            f"{hop['median_us']:.1f} us, p99 {hop['p99_us']:.1f} us | ~2 ms | hop_cuda_vits-1080p.json |"
        )
    return "\n".join(rows)


def _camera_rows(c: dict[str, Any]) -> list[str]:
    """`vpengine bench cameras`: the stream of several cameras at their rate, and batched vs separate engines."""
    heads = "+".join(c.get("heads", []))
    rows = []
    s = c.get("stream")
    if s:
        lat = s["latency_all_heads_ms"]
        skipped = ", ".join(f"{m} {n['skipped']}" for m, n in s["counted"].items() if n["skipped"])
        memory = s["device_memory_bytes"]
        memory_text = "not measured" if memory is None else f"{memory / 2**30:.2f} GiB"
        rows.append(
            f"| {s['cameras']} cameras at {s['fps_per_camera']:g} Hz each, {heads} (thread mode) | submit -> every "
            f"head: p50 {lat['p50']:.1f} ms, p99 {lat['p99']:.1f} ms; {s['frames_all_heads']} of "
            f"{s['frames_submitted']} frames through every head (skipped, counted: {skipped or 'none'}); device "
            f"memory {memory_text} | target: p99 <= 33 ms, <= 2.5 GiB | {c['file']} |"
        )
    if c.get("throughput"):
        points = ", ".join(
            f"{t['cameras']}: {t['batched_fps']:.0f} vs {t['separate_fps']:.0f} ({t['ratio']:.2f}x)"
            for t in c["throughput"]
        )
        rows.append(
            f"| cameras: one engine batched vs separate engines, frames/s ({heads}) | {points} | target: >= 1.5x "
            f"at 4 cameras | {c['file']} |"
        )
    return rows


def _memory(flat: bool | None) -> str:
    return "device memory not measured" if flat is None else f"memory flat: {flat}"


def _floor_row(f: dict[str, Any]) -> str:
    """A floor run: the engine's mean frame in each mode, submitted and written in place, and where the device times
    were measured (CUDA) the three floors and how far over the summed one each mean is, a frame's share of a
    batch's back-to-back device time for each batch size measured, and for each batch of several frames a frame's
    share pipelined against as many sets of one frame side by side, and their ratio (what batching buys there)."""
    heads = "+".join(f.get("heads") or [k for k in f["device_ms"] if k != "foundation"])
    if "floor_sum_ms" in f:
        floors = (
            f"floor {f['floor_sum_ms']:.2f} ms summed, {f['floor_with_transfers_ms']:.2f} ms with the frame's upload "
            f"and the results' download, {f['chained_ms']['compute']:.2f} ms back to back on one stream; "
        )
        batches = sorted(f.get("by_batch", {}).items(), key=lambda kv: int(kv[0]))
        if batches:
            floors += (
                "a frame back to back in a batch of "
                + ", ".join(f"{n}: {b['chained_ms_a_frame']:.2f} ms" for n, b in batches)
                + "; "
            )
            gains = [(n, b) for n, b in batches if "batching_gain" in b and int(n) > 1]  # older files lack it
            if gains:
                floors += (
                    "pipelined, a batch against as many engines of one frame: "
                    + ", ".join(
                        f"{n}: {b['pipelined_ms_a_frame']:.2f} against {b['separate_pipelined_ms_a_frame']:.2f} ms "
                        f"(batching {b['batching_gain']:.2f}x)"
                        for n, b in gains
                    )
                    + "; "
                )
    else:
        floors = "no device times off CUDA; "

    def mode(m: str) -> str:
        parts = []
        for key, what in ((m, "submitted"), (f"{m}_frame_slot", "written in place")):
            over = f" ({f[f'{key}_overhead_vs_floor']:+.0%})" if f"{key}_overhead_vs_floor" in f else ""
            parts.append(f"{f[key]['mean']:.2f} ms {what}{over}")
        return f"{m} mode " + ", ".join(parts)

    return (
        f"| engine vs device-time floor ({setup_label(f['setup'], det='det' in heads)}{'; ' * bool(heads)}{heads}) "
        f"| {floors}"
        f"{mode('thread')}; {mode('process')} | - | {f['file']} |"
    )


def headline(key: str, run: dict[str, Any]) -> dict[str, float]:
    """The numbers (ms) a before/after comparison looks at: the engine's mean frame at the largest head count (E1,
    E2), a frame's three results at p50 and p99 (E5), the engine's mean frame in each mode (floor), the stream's
    every-head latency and a batched round's time at each camera count (cameras)."""
    if key in ("E1", "E2"):
        last = run["rows"][-1]
        return {f"engine, {last['heads']} heads, mean": last["engine"]["mean"]}
    if key == "E5":
        a = run["all_three_latency_ms"]
        return {"all three, p50": a["p50"], "all three, p99": a["p99"]}
    if key == "floor":
        return {
            f"{m} mode{', written in place' if slot else ''}, mean": run[f"{m}{'_frame_slot' if slot else ''}"]["mean"]
            for m in ("thread", "process")
            for slot in (False, True)
        }
    if key == "cameras":
        out: dict[str, float] = {}
        if run.get("stream"):
            lat = run["stream"]["latency_all_heads_ms"]
            out |= {"stream, every head, p50": lat["p50"], "stream, every head, p99": lat["p99"]}
        for t in run.get("throughput", []):
            out[f"batched, {t['cameras']} cameras, a round"] = 1000 * t["cameras"] / t["batched_fps"]
        return out
    return {}


def comparison(r: dict[str, Any], baseline: str) -> str:
    """Each run against the newest run of its experiment in a file whose name holds ``baseline``: a markdown table
    of the headline numbers and the change (+ is slower)."""
    rows = [
        "| experiment | measure | baseline (ms) | run (ms) | change | run's file |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for key in ("E1", "E2", "E5", "floor", "cameras"):
        runs = r.get(f"{key}_all", [])
        base = [x for x in runs if baseline in x["file"]]
        if not base:
            continue
        ref = headline(key, base[-1])
        for run in runs:
            if baseline in run["file"]:
                continue
            for measure, value in headline(key, run).items():
                if measure in ref:
                    rows.append(
                        f"| {key} | {measure} | {ref[measure]:.2f} | {value:.2f} | {value / ref[measure] - 1:+.1%} | "
                        f"{run['file']} |"
                    )
    return "\n".join(rows)


# ---------------------------------------------------------------------------------------------------- figure
def _e1(ax: Any, r: dict[str, Any]) -> None:
    rows = r["E1"]["rows"]
    ns = [x["heads"] for x in rows]
    for s, style in (("engine", "o-"), ("independent", "s--"), ("sequential", "^:")):
        ax.plot(ns, [x[s]["hz"] for x in rows], style, label=s)
    ax.set_xticks(ns)
    ax.set(
        xlabel="depth heads",
        ylabel="frames/s, one frame in flight",
        title=f"E1: shared backbone vs not\n({setup_label(r['E1']['setup'])})",
    )
    ax.legend()


def _e2(ax: Any, r: dict[str, Any]) -> None:
    rows = r["E2"]["rows"]
    ns = [x["heads"] for x in rows]
    for s, style in (("engine", "o-"), ("sequential", "^:")):
        ax.plot(ns, [x[s]["hz"] for x in rows], style, label=s)
    ax.set_xticks(ns)
    ax.set(
        xlabel="detection heads",
        ylabel="frames/s",
        title=f"E2: parallel vs sequential heads\n({setup_label(r['E2']['setup'], det=True)})",
    )
    ax.legend()


def _e3(ax: Any, r: dict[str, Any]) -> None:
    rows = r["E3"]["rows"]
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [y["mps_off"]["hz"] for y in rows], 0.4, label="MPS off")
    ax.bar(x + 0.2, [y["mps_on"]["hz"] for y in rows], 0.4, label="MPS on")
    ax.set_xticks(x, [f"{y['head']} x{y['heads']}" for y in rows])
    ax.set(ylabel="frames/s", title=f"E3: CUDA MPS\n({setup_label(r['E3']['setup'], det=True)})")
    ax.legend()


def _e4(ax: Any, r: dict[str, Any]) -> None:
    rows = r["E4"]["rows"]
    rates = [x["rate_hz"] for x in rows]
    ax.plot(rates, [x["ideal"] for x in rows], "k--", label="ideal")
    ax.plot(rates, [x["runs"] for x in rows], "o", label="measured")
    ax.set(
        xlabel="rate limit (Hz)",
        ylabel=f"runs in {r['E4']['input_seconds']:.0f} s",
        title="E4: rate limits (30 Hz input)",
    )
    ax.legend()


def _e5_latency(ax: Any, r: dict[str, Any]) -> None:
    lat = r["E5"]["per_head_latency_ms"]
    names = list(lat)
    x = np.arange(len(names))
    ax.bar(x - 0.2, [lat[n]["p50"] for n in names], 0.4, label="p50")
    ax.bar(x + 0.2, [lat[n]["p99"] for n in names], 0.4, label="p99")
    ax.set_xticks(x, names)
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


def floor_panel_rows(r: dict[str, Any]) -> list[tuple[str, float, float, float]]:
    """The floor panel's runs, newest last: (file name less ``paper_`` and ``.json``, summed device time, the same
    with the frame's upload and the results' download, the engine's thread-mode mean from a frame slot), in ms; only
    runs with device times (CUDA)."""
    rows = [
        (
            f["file"].removeprefix("paper_").removesuffix(".json"),
            f["floor_sum_ms"],
            f["floor_with_transfers_ms"],
            f["thread_frame_slot"]["mean"],
        )
        for f in r.get("floor_all", [])
        if "floor_sum_ms" in f
    ]
    return rows[-FLOOR_RUNS_DRAWN:]


def _floor(ax: Any, r: dict[str, Any]) -> None:
    rows = floor_panel_rows(r)
    y = np.arange(len(rows))
    over = [100 * (x[3] / x[1] - 1) for x in rows]
    xfer = [100 * (x[2] / x[1] - 1) for x in rows]
    ax.barh(y - 0.2, xfer, 0.4, color="#bbbbbb", label="the frame's upload and the results' download alone")
    ax.barh(y + 0.2, over, 0.4, color="#4a7fc0", label="engine, thread mode, frame written in place (mean)")
    for yi, v in zip(y, over):
        ax.text(v, yi + 0.2, f" {v:+.0f}%", va="center", fontsize=7)
    ax.axvline(20, color="#c04040", lw=1, ls="--", label="target: +20%")
    ax.set_yticks(y, [x[0] for x in rows], fontsize=7)
    ax.invert_yaxis()
    ax.set(xlabel="% over the models' summed device time", title="engine vs device-time floor (newest runs)")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=1, frameon=False)


def _cameras(ax: Any, r: dict[str, Any]) -> None:
    c = [x for x in r["cameras_all"] if x.get("throughput")][-1]
    n = [t["cameras"] for t in c["throughput"]]
    x = list(range(len(n)))
    ax.bar([i - 0.2 for i in x], [t["batched_fps"] for t in c["throughput"]], 0.4, label="one engine, batched")
    ax.bar([i + 0.2 for i in x], [t["separate_fps"] for t in c["throughput"]], 0.4, label="one engine per camera")
    for i, t in zip(x, c["throughput"]):
        ax.text(i, max(t["batched_fps"], t["separate_fps"]), f"{t['ratio']:.2f}x", ha="center", va="bottom")
    ax.set_xticks(x, [str(k) for k in n])
    ax.margins(y=0.12)
    ax.set(xlabel="cameras", ylabel="frames/s through every head", title="several cameras: batched vs apart")
    ax.legend(fontsize=7)


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
        _cameras: any(x.get("throughput") for x in r.get("cameras_all", [])),
    }
    return [draw for draw, present in have.items() if present]


def _all_runs(r: dict[str, Any]) -> list[dict[str, Any]]:
    """Every run the folder has: the paper's experiments' and the cameras benchmark's."""
    return [run for key in PAPER for run in r.get(f"{key}_all", [])] + r.get("cameras_all", [])


def _newest_machine(r: dict[str, Any]) -> dict[str, Any]:
    runs = _all_runs(r)
    return max(runs, key=lambda x: x["date"])["machine"] if runs else {}


def build_figure(r: dict[str, Any]) -> Any:
    """One panel per experiment the folder has results for, three to a row (none: a figure saying so)."""
    from vpengine.bench.common import pyplot

    plt = pyplot()
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
    machine = _newest_machine(r)
    fig.suptitle(f"vpengine on {machine.get('gpu') or machine.get('cpu', '?')}")
    fig.tight_layout()
    return fig


def main(args: argparse.Namespace) -> int:
    from vpengine.bench.common import pyplot

    folder = Path(args.results)
    if not folder.is_dir():
        raise ValueError(f"--results {args.results!r} is not a folder")
    r = collect(folder)
    unread = None
    if not _all_runs(r) and not set(OTHER_FILES) & {p.name for p in folder.iterdir()}:
        # nothing it reads: say what it reads and what is there, on the terminal and in the summary
        here = sorted(p.name for p in folder.glob("*.json"))
        below = sorted(
            {p.parent.name for pattern in ("*/paper_*.json", "*/cameras_*.json") for p in folder.glob(pattern)}
        )
        unread = (
            f"No results this report reads here (paper_*.json, cameras_*.json, {', '.join(OTHER_FILES)})"
            + (f"; its JSON files: {', '.join(here[:6])}{' ...' if len(here) > 6 else ''}" if here else "")
            + (f"; folders with results below it: {', '.join(below[:6])} (give one as --results)" if below else "")
            + "."
        )
        print(f"vpengine bench report: WARNING: {unread}", file=sys.stderr)
    machines = sorted({machine_label(run["machine"]) for run in _all_runs(r)})
    md = [f"# vpengine benchmarks: {folder.name}", ""]
    md += [f"Machine: {m}" for m in machines] or [unread or "No results in this folder."]
    md += ["", table(r)]
    if args.baseline:
        md += [
            "",
            f"## Against the baseline (files named *{args.baseline}*)",
            "",
            comparison(r, args.baseline),
        ]
    text = "\n".join(md) + "\n"
    out = Path(args.out) if getattr(args, "out", None) else folder  # `vpengine bench` always gives --out
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.md").write_text(text)
    fig = build_figure(r)
    fig.savefig(out / "summary.png")
    pyplot().close(fig)
    print(text)
    print(f"-> {out / 'summary.md'}, {out / 'summary.png'}")
    return 0
