"""The README's main job on the whole street video, as a benchmark: ``vpengine run`` over vtest.avi with ``--viz``.

Writes the run's summary, the table it printed, the machine (and its load: the CPU is shared) and the size of what
it wrote, per head and in all, to benchmarks/results/run_street_viz_cpu.json (the numbers the README quotes). Depth
is written as 16-bit PNG, the default; the same run with ``--depth-format npy`` (float32, as every release before
did) is measured too, for the size alone. Run from the repo root: ``.venv/bin/python benchmarks/run_street_viz.py``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from vpengine.bench.common import machine_info

ROOT = Path(__file__).resolve().parents[1]
VIDEO = ROOT.parent / "shared" / "data" / "media" / "vtest.avi"
OUT = ROOT / "benchmarks" / "results" / "run_street_viz_cpu.json"


def run(*extra: str) -> tuple[list[str], subprocess.CompletedProcess, dict, dict[str, int]]:
    exe = Path(sys.executable).with_name("vpengine")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "demo"
        cmd = [
            str(exe),
            "run",
            "--config",
            "tiny",
            "--source",
            str(VIDEO),
            "--out",
            str(out),
            "--viz",
            *extra,
        ]
        p = subprocess.run([*cmd, "--no-progress"], cwd=ROOT, capture_output=True, text=True, check=True)
        summary = json.loads((out / "summary.json").read_text())
        sizes = {
            d.name: sum(f.stat().st_size for f in d.rglob("*") if f.is_file())
            for d in out.iterdir()
            if d.is_dir()
        }
        sizes["all"] = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
        shown = " ".join(["vpengine", *cmd[1:]]).replace(str(VIDEO), "../shared/data/media/vtest.avi")
        return [shown.replace(str(out), "TMP/demo")], p, summary, sizes


def main() -> int:
    load_before = os.getloadavg()
    (command,), p, summary, sizes = run()
    _, _, _, sizes_npy = run("--depth-format", "npy")
    result = {
        "command": command,
        "machine": machine_info(),
        "load_average_1_5_15min_before": load_before,
        "printed": p.stdout.strip().splitlines(),
        "bytes_written": sizes["all"],
        "bytes_written_by_head": {k: v for k, v in sizes.items() if k != "all"},
        "bytes_written_with_depth_format_npy": sizes_npy["all"],
        "summary": summary,
    }
    OUT.write_text(json.dumps(result, indent=2) + "\n")
    print("\n".join(result["printed"]))
    print(
        f"{sizes['all'] / 1e9:.2f} GB written ({sizes_npy['all'] / 1e9:.2f} GB with --depth-format npy); "
        f"results in {OUT.relative_to(ROOT)}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
