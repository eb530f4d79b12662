"""What the engine's own work allows: frames per second through a thread-mode engine whose models cost nothing.

Every model's call returns its first outputs again, so what is left is the engine: submitting and fitting frames,
the mailboxes and their locks, batching the cameras' frames, copying outputs, counting, answering the callers. In
thread mode all of it shares one interpreter, so this is the ceiling a fast GPU meets when the host is the
bottleneck. Each run is a fresh interpreter running the batched engine of ``--cameras`` cameras (the tiny config,
each camera pumped by its own thread with a file run's frames in flight, as ``vpengine bench cameras`` does) for
``--seconds``; ``--src`` trees (one or several: an older one for a before/after) take turns, ``--rounds`` each::

    python benchmarks/engine_overhead.py --out benchmarks/results
    python benchmarks/engine_overhead.py --src .before/src --src src --tags before,after --out DIR

Writes ``DIR/engine_overhead_cpu.json`` with the machine.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

from vpengine.bench.common import add_tree_arguments, run_in_tree, trees, write_results

ONE = """
import json, sys
from vpengine.backends.eager import EagerExecutor
first = EagerExecutor.__call__
def no_cost(self, inputs):  # the first outputs of each batch size, again
    done = self.__dict__.setdefault("_no_cost", {})
    n = next(iter(inputs.values())).shape[0]
    if n not in done:
        done[n] = first(self, inputs)
    return done[n]
EagerExecutor.__call__ = no_cost
from vpengine.bench import cameras as bc
from vpengine.bench.paper.harness import Bench, engines
from vpengine.config import load_config
from vpengine.pipeline.pacing import pipelined
n, seconds = int(sys.argv[1]), float(sys.argv[2])
base = load_config("tiny", ["mode=thread", "device=cpu"])
imgs = Bench(base).images()
cfg, in_flight = pipelined(bc._config(base, n))
heads = {h.name for h in base.heads}
with engines([cfg]) as (eng,):
    cams = eng.cameras if n > 1 else [None]
    bc._all_cameras([(eng, c) for c in cams], imgs, 5, 0.0, in_flight, heads)
    fps, frames, torn, _ = bc._all_cameras([(eng, c) for c in cams], imgs, 50, seconds, in_flight, heads)
print(json.dumps({"fps": fps, "frames": frames, "torn": torn}))
"""


def run(src: str, cameras: int, seconds: float) -> dict[str, float]:
    what = f"a run of {src} with {cameras} cameras"
    return run_in_tree(src, ONE, [str(cameras), str(seconds)], what, timeout=seconds + 300)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_tree_arguments(p)
    p.add_argument("--cameras", default="1,4", help="camera counts (default 1,4)")
    p.add_argument("--seconds", type=float, default=5.0, help="length of each run (default 5)")
    p.add_argument("--rounds", type=int, default=5, help="runs of each tree and camera count (default 5)")
    p.add_argument("--out", default=".", help="results folder")
    args = p.parse_args()
    tags, srcs = zip(*trees(p, args, Path(__file__).resolve().parents[1] / "src"))
    res: dict[str, dict[str, list[float]]] = {t: {} for t in tags}
    torn = {t: 0 for t in tags}  # frames that came back without some head's output, by tree
    for n in (int(c) for c in args.cameras.split(",")):
        for r in range(args.rounds):  # the trees take turns: a busy machine's drift falls on both
            for tag, src in zip(tags, srcs):
                one = run(src, n, args.seconds)
                fps, torn[tag] = one["fps"], torn[tag] + one["torn"]
                res[tag].setdefault(str(n), []).append(fps)
                missing = f", {one['torn']} frames missing a head" if one["torn"] else ""
                print(f"{tag}, {n} cameras, round {r + 1}: {fps:.1f} frames/s{missing}", flush=True)
    summary = {
        t: {n: {"median_fps": statistics.median(v), "runs": v} for n, v in by_n.items()} for t, by_n in res.items()
    }
    for t, by_n in summary.items():
        print(t, ", ".join(f"{n} cameras {s['median_fps']:.1f} frames/s" for n, s in by_n.items()))
    data = {"seconds": args.seconds, "trees": dict(zip(tags, srcs)), "results": summary, "frames_missing_a_head": torn}
    print(write_results(args.out, "engine_overhead_cpu", data))
    return 0


if __name__ == "__main__":
    sys.exit(main())
