"""The README's main job, as a benchmark: ``vpengine run`` over the street video with ``--viz``.

Writes the run's summary, the table it printed, the machine and the size of what it wrote to
benchmarks/results/run_street_viz_cpu.json (the numbers the README's Quick start quotes). Run from the repo root:
``.venv/bin/python benchmarks/run_street_viz.py``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from vpengine.bench.common import machine_info

ROOT = Path(__file__).resolve().parents[1]
VIDEO = ROOT.parent / "shared" / "data" / "media" / "vtest.avi"
OUT = ROOT / "benchmarks" / "results" / "run_street_viz_cpu.json"


def main() -> int:
    exe = Path(sys.executable).with_name("vpengine")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "demo"
        cmd = [
            str(exe),
            "run",
            "--config",
            "configs/tiny.yaml",
            "--source",
            str(VIDEO),
            "--out",
            str(out),
            "--viz",
        ]
        p = subprocess.run([*cmd, "--no-progress"], cwd=ROOT, capture_output=True, text=True, check=True)
        summary = json.loads((out / "summary.json").read_text())
        written = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    result = {
        "command": " ".join(["vpengine", *cmd[1:]])
        .replace(str(VIDEO), "../shared/data/media/vtest.avi")
        .replace(str(out), "TMP/demo"),
        "machine": machine_info(),
        "printed": p.stdout.strip().splitlines(),
        "bytes_written": written,
        "summary": summary,
    }
    OUT.write_text(json.dumps(result, indent=2) + "\n")
    print("\n".join(result["printed"]))
    print(f"{written / 1e9:.2f} GB written; results in {OUT.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
