"""The README's main job as a benchmark: ``vpengine run --config tiny --viz`` over a street video.

Writes the run's summary, the table it printed, the machine (and its load: the CPU is shared) and the size of what
it wrote, per head and in all, to ``OUT/run_street_viz_cpu.json``. Depth is written as 16-bit PNG, the default; the
same run with ``--depth-format npy`` (float32, as every release before did) is measured too, for the size alone.

::

    python benchmarks/run_street_viz.py                                  # the 50 frames that ship (sample:street)
    python benchmarks/run_street_viz.py --source vtest.avi --out DIR      # the README's numbers: all 795 frames

The source defaults to the street sample that ships with vpengine, so it runs from a clone as it is; the README's
numbers come from the whole of OpenCV's ``vtest.avi`` (its first 5 s are the sample). ``OUT`` defaults to a new
folder ``run-street-viz-<date>-<time>`` in the current folder, never the clone's tracked ``benchmarks/results``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from vpengine.bench.common import machine_info

RESULTS = "run_street_viz_cpu.json"


def run(source: str, max_frames: int | None, *extra: str) -> tuple[str, subprocess.CompletedProcess, dict, dict]:
    """One ``vpengine run`` into a folder of its own: (the command as shown, the process, summary, bytes by head)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "demo"
        args = ["run", "--config", "tiny", "--source", source, "--out", str(out), "--viz", *extra]
        if max_frames is not None:
            args += ["--max-frames", str(max_frames)]
        cmd = [sys.executable, "-m", "vpengine.cli.main", *args, "--no-progress"]
        p = subprocess.run(cmd, capture_output=True, text=True)
        if p.returncode != 0:
            raise SystemExit(f"run_street_viz: vpengine run failed ({p.returncode}): {p.stderr.strip()[-2000:]}")
        summary = json.loads((out / "summary.json").read_text())
        sizes = {
            d.name: sum(f.stat().st_size for f in d.rglob("*") if f.is_file()) for d in out.iterdir() if d.is_dir()
        }
        sizes["all"] = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
        shown = " ".join(["vpengine", *args]).replace(str(out), "TMP/demo")
        if Path(source).exists():
            shown = shown.replace(source, Path(source).name)  # the file, not where it lay on this machine
        return shown, p, summary, sizes


def out_folder(out: str | None) -> Path:
    """``out`` (made if missing), or a new ``run-street-viz-<date>-<time>`` folder here."""
    if out is not None:
        path = Path(out)
        path.mkdir(parents=True, exist_ok=True)
        return path
    stamp = time.strftime("%Y%m%d-%H%M%S")
    for n in range(1, 1000):
        path = Path(f"run-street-viz-{stamp}" + (f"-{n}" if n > 1 else ""))
        try:
            path.mkdir()
            return path
        except FileExistsError:
            continue
    raise SystemExit(f"run_street_viz: no free folder name run-street-viz-{stamp}-N here; give --out")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--source", "-s", default="sample:street", help="the video (default: sample:street, 50 frames)")
    p.add_argument("--out", "-o", help="folder for the results (default: a new run-street-viz-<date>-<time> here)")
    p.add_argument("--max-frames", type=int, help="stop after this many frames (default: the whole video)")
    args = p.parse_args(argv)
    out = out_folder(args.out)
    load_before = os.getloadavg()
    command, proc, summary, sizes = run(args.source, args.max_frames)
    _, _, _, sizes_npy = run(args.source, args.max_frames, "--depth-format", "npy")
    result = {
        "command": command,
        "machine": machine_info(),
        "load_average_1_5_15min_before": load_before,
        "printed": proc.stdout.strip().splitlines(),
        "bytes_written": sizes["all"],
        "bytes_written_by_head": {k: v for k, v in sizes.items() if k != "all"},
        "bytes_written_with_depth_format_npy": sizes_npy["all"],
        "summary": summary,
    }
    path = out / RESULTS
    path.write_text(json.dumps(result, indent=2) + "\n")
    print("\n".join(result["printed"]))
    print(
        f"{sizes['all'] / 1e9:.2f} GB written ({sizes_npy['all'] / 1e9:.2f} GB with --depth-format npy); "
        f"results in {path}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
