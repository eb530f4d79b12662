"""How long a process-mode engine takes to start, and what its child processes spend doing it.

Each run is a fresh interpreter that starts the engine (every worker built, warmed up and serving), stops it, and
reports the wall time of ``start()`` and ``getrusage(RUSAGE_CHILDREN)``: the CPU seconds of every process the
engine started (the worker zygote reaps the workers, the engine reaps the zygote; Note [Child lifecycle] in
runtime/process.py). Only the public API is used, so ``--src`` can point at an older tree for a before/after in
one call::

    python benchmarks/process_start.py --out DIR                                   # tiny models on the CPU
    python benchmarks/process_start.py --config bench --device cuda --random-weights --out DIR --tag after
    python benchmarks/process_start.py --src .before/src --config bench --device cuda --random-weights --tag before

Writes ``DIR/process_start_<device>[_TAG].json`` with the machine (and its load: a shared CPU is noted).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from vpengine.bench.common import write_results

ONE = """
import json, resource, sys, time
from vpengine.config import load_config
from vpengine.engine import Engine
cfg = load_config(sys.argv[1], sys.argv[2:])
t = time.monotonic()
e = Engine(cfg).start()
start_s = time.monotonic() - t
e.stop()
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({"start_s": start_s, "children_cpu_s": ru.ru_utime + ru.ru_stime, "workers": len(cfg.model_names())}))
"""


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--src", help="the tree's src/ folder to import vpengine from (default: the one running this)")
    p.add_argument("--config", default="tiny", help="a shipped config's name or a file (default: tiny)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--random-weights", action="store_true", help="weights.random_weights=true (no checkpoints)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--tag", default="")
    p.add_argument("--out", default="process-start", help="results folder (default: ./process-start)")
    args = p.parse_args()
    overrides = ["mode=process", f"device={args.device}", *args.overrides]
    if args.random_weights:
        overrides.append("weights.random_weights=true")
    env = dict(os.environ)
    if args.src:
        env["PYTHONPATH"] = os.pathsep.join([str(Path(args.src).resolve()), env.get("PYTHONPATH", "")])
    runs = []
    for _ in range(args.runs):
        out = subprocess.run(
            [sys.executable, "-c", ONE, args.config, *overrides], env=env, capture_output=True, text=True, timeout=600
        )
        if out.returncode != 0:
            sys.exit(f"the engine did not start:\n{out.stderr[-3000:]}")
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(f"started in {runs[-1]['start_s']:.2f} s, children {runs[-1]['children_cpu_s']:.2f} CPU-s", flush=True)
    summary = {k: statistics.median(r[k] for r in runs) for k in ("start_s", "children_cpu_s")}
    name = f"process_start_{args.device.split(':')[0]}" + (f"_{args.tag}" if args.tag else "")
    data = {"config": args.config, "overrides": overrides, "src": args.src, "runs": runs}
    path = write_results(args.out, name, {**data, "median": summary})
    print(f"median: started in {summary['start_s']:.2f} s, children {summary['children_cpu_s']:.2f} CPU-s -> {path}")


if __name__ == "__main__":
    main()
