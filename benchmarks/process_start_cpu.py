"""CPU seconds that starting (and stopping) a process-mode tiny engine (foundation + 3 heads) costs its child
processes: the zygote and the workers (Note [Child lifecycle] in runtime/process.py).

Each run is a fresh interpreter, so ``getrusage(RUSAGE_CHILDREN)`` after ``stop()`` counts exactly that engine's
processes (the zygote reaps the workers, the engine reaps the zygote). Prints JSON with the machine (its load
too: the CPU may be shared). Run from the repo root: ``.venv/bin/python benchmarks/process_start_cpu.py [runs]``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from vpengine.bench.common import machine_info

ROOT = Path(__file__).resolve().parents[1]
ONE = """
import json, resource, time
from vpengine.config import load_config
from vpengine.engine import Engine
t = time.monotonic()
e = Engine(load_config({config!r}, ["mode=process", "device=cpu"])).start()
start_s = time.monotonic() - t
e.stop()
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({{"children_cpu_s": ru.ru_utime + ru.ru_stime, "start_wall_s": start_s}}))
"""


def main() -> None:
    runs = int(sys.argv[1]) if len(sys.argv) > 1 else 3
    code = ONE.format(config=str(ROOT / "configs" / "tiny.yaml"))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    results = []
    for _ in range(runs):
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
        results.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(json.dumps({"machine": machine_info(), "workers": 4, "runs": results}, indent=2))


if __name__ == "__main__":
    main()
