"""Shared by the benchmarks: machine description, results files, device timing and figures."""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any


def proc_stat(path: str) -> list[str]:
    """The fields of a ``/proc/<pid>/stat`` (or ``/proc/<pid>/task/<tid>/stat``) after the command name, which may
    hold spaces and parentheses: state, ppid, ... (``proc(5)``'s fields from the third on). OSError if it is gone."""
    with open(path) as f:
        return f.read().rsplit(")", 1)[1].split()


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, Any]:
    import torch

    info: dict[str, Any] = {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "memory_gb": round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "platform": platform.platform(),
    }
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        info["gpu"] = p.name
        info["gpu_memory_gb"] = round(p.total_memory / 2**30, 1)
        info["cuda"] = torch.version.cuda
    return info


def add_tree_arguments(p: argparse.ArgumentParser) -> None:
    """``--src`` (repeat) and ``--tags``: the trees a before/after benchmark runs side by side (``trees``)."""
    p.add_argument("--src", action="append", help="a tree's src/ folder (repeat; default: this one's)")
    p.add_argument("--tags", default="", help="a name for each --src, comma-separated")


def trees(p: argparse.ArgumentParser, args: argparse.Namespace, default_src: Path) -> list[tuple[str, str]]:
    """(tag, src folder) of each tree ``--src`` names (``default_src`` without any), or the parser's error."""
    srcs = args.src or [str(default_src)]
    tags = [t for t in args.tags.split(",") if t] or [f"tree{i}" for i in range(len(srcs))]
    if len(tags) != len(srcs):
        p.error(f"--tags names {len(tags)} trees, --src gives {len(srcs)}")
    return list(zip(tags, srcs))


def run_in_tree(
    src: str, code: str, argv: list[str], what: str, timeout: float, env: dict[str, str] | None = None
) -> Any:
    """Run Python ``code`` with ``argv`` in a fresh interpreter importing vpengine from ``src`` (and ``env`` added to
    the environment): the JSON its last line of output prints. RuntimeError naming ``what`` and the error output if
    it fails."""
    path = [str(Path(src).resolve()), *filter(None, [os.environ.get("PYTHONPATH")])]
    full = dict(os.environ, **(env or {}), PYTHONPATH=os.pathsep.join(path))
    out = subprocess.run([sys.executable, "-c", code, *argv], env=full, capture_output=True, text=True, timeout=timeout)
    lines = out.stdout.strip().splitlines()
    if out.returncode != 0 or not lines:
        raise RuntimeError(f"{what} failed ({out.returncode}):\n{out.stderr[-3000:]}")
    return json.loads(lines[-1])


def write_results(out_dir: str | Path, name: str, data: dict[str, Any]) -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.json"
    payload = {
        "benchmark": name,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": machine_info(),
        **data,
    }
    path.write_text(json.dumps(payload, indent=2) + "\n")
    return path


def event_ms(run: Any, n: int, warmup: int = 0) -> float:
    """Median device time (ms) of ``run()`` over ``n`` calls, between CUDA events on the current stream, after
    ``warmup`` calls not timed."""
    import numpy as np
    import torch

    for _ in range(warmup):
        run()
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    times = []
    for _ in range(n):
        start.record()
        run()
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end))
    return float(np.median(times))


def pyplot() -> Any:
    """matplotlib.pyplot drawing to files only (the Agg backend: no display needed); figures need the extra
    ``vpengine[plots]`` (``vpengine bench`` names it when matplotlib is missing)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
