"""What a first start compiles: each compiled model's set-up time from a cold compile cache, the graphs it compiled,
and its time on each batch size, for one or several trees side by side (Note [One compile for every batch] in
backends/compiled.py).

Each tree runs in a fresh interpreter with a compile cache of its own, empty (a first start): the config's models
(``bench`` by default: DINOv2 ViT-S/14, depth, segmentation and detection at 1080p, fp16) built with random weights
and set up by the compile backend with their configured options (the foundation model always, its features feed
the heads; heads of another backend are left out) for batches of 1 to ``--max-batch``, as an engine of that many
cameras sets them up; then each batch size timed over ``--runs`` calls back to back (ms a call between CUDA events
on the stream, launches included; wall time on the CPU). The heads read the first frames of the foundation model's
features for the largest batch, each tree its own. Each tree's outputs for a frame alone, a batch of 2 and the
largest batch are compared with the first tree's: a floating output by its largest absolute difference, an integer
one (a class map, labels, a count) by the share of its elements that differ (a class id that differs is wrong by
any amount). Each tree is named by its compile cache key (a digest of its source, Note [Compile cache key])::

    python benchmarks/compile_batches.py --max-batch 8 --out benchmarks/results/h200
    python benchmarks/compile_batches.py --src .before/src --src src --tags before,after --out DIR
    python benchmarks/compile_batches.py -c tiny --set heads.depth.backend=compile --max-batch 3 --out DIR  # CPU

Writes ``DIR/compile_batches_<device>.json`` with the machine.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from vpengine.bench.common import add_tree_arguments, run_in_tree, trees, write_results

if TYPE_CHECKING:
    import torch

ONE = """
import json, sys, time
import torch
import torch._dynamo.utils as U
from vpengine.backends import make_executor
from vpengine.backends.compile_cache import compile_key
from vpengine.config import load_config
from vpengine.models.build import build_model, frame_spec
config, device, n, runs, saved, sets = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5], sys.argv[6:]
cfg = load_config(config, [f"device={device}", *sets])
dev = torch.device(device)
cuda = dev.type == "cuda"
compared = sorted({1, min(2, n), n})  # a frame alone, and both ends of the batches that share a graph

def timed(ex, inputs):
    ms, outs = {}, {}
    for b in range(1, n + 1):
        args = {k: v[:b] for k, v in inputs.items()}
        for _ in range(5):
            ex(args)
        if cuda:
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
        t = time.perf_counter()
        for _ in range(runs):
            ex(args)
        if cuda:
            end.record()
            end.synchronize()
        ms[b] = start.elapsed_time(end) / runs if cuda else (time.perf_counter() - t) * 1e3 / runs
        if b in compared:
            outs[b] = {k: v.cpu() for k, v in ex(args).items()}
    return ms, outs

def set_up(model, name, mcfg):
    graphs, t = U.counters["stats"]["unique_graphs"], time.perf_counter()
    precision = mcfg.precision or cfg.precision
    ex = make_executor(model, "compile", dev, name, options=mcfg.backend_options, precision=precision, max_batch=n)
    return ex, {"setup_s": time.perf_counter() - t, "graphs": U.counters["stats"]["unique_graphs"] - graphs}

torch.manual_seed(0)
rows, outputs = {}, {}
fm = build_model(cfg, "foundation", "foundation", frame_spec(cfg), {}, dev, False)
ex, rows["foundation"] = set_up(fm, "foundation", cfg.foundation_model)
frames = torch.randint(0, 255, (n, cfg.input.height, cfg.input.width, 3), dtype=torch.uint8, device=dev)
features = {k: v.clone() for k, v in ex({"frame": frames}).items()}
rows["foundation"]["ms"], outputs["foundation"] = timed(ex, {"frame": frames})
del ex
for h in cfg.heads:
    if h.backend != "compile":
        continue
    torch.manual_seed(1)
    head = build_model(cfg, h.name, "head", fm.output_spec, fm.meta, dev, False)
    ex, rows[h.name] = set_up(head, h.name, h)
    rows[h.name]["ms"], outputs[h.name] = timed(ex, {k: features[k] for k in head.input_spec})
    del ex
torch.save(outputs, saved)
print(json.dumps({"compile_key": compile_key(), "models": rows}))
"""


def run(src: str, config: str, sets: list[str], device: str, n: int, runs: int, saved: Path) -> dict:
    with tempfile.TemporaryDirectory() as cache:  # a first start: nothing compiled yet
        env = {"TORCHINDUCTOR_CACHE_DIR": f"{cache}/inductor", "TRITON_CACHE_DIR": f"{cache}/triton"}
        argv = [config, device, str(n), str(runs), str(saved), *sets]
        return run_in_tree(src, ONE, argv, f"the run of {src}", timeout=3600, env=env)


def main() -> int:
    import torch

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_tree_arguments(p)
    p.add_argument("--config", "-c", default="bench", help="engine config (default: the shipped bench config)")
    p.add_argument("--set", action="append", default=[], help="a config override, key=value (repeat)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--max-batch", type=int, default=8, help="batches of 1 to this many frames (default 8)")
    p.add_argument("--runs", type=int, default=50, help="timed calls of each batch size (default 50)")
    p.add_argument("--out", default=".", help="results folder")
    args = p.parse_args()
    tags, srcs = zip(*trees(p, args, Path(__file__).resolve().parents[1] / "src"))
    if args.max_batch < 1:
        p.error(f"--max-batch {args.max_batch}: at least 1")
    res: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        saved = {t: Path(tmp) / f"{t}.pt" for t in tags}
        for tag, src in zip(tags, srcs):
            res[tag] = run(src, args.config, args.set, args.device, args.max_batch, args.runs, saved[tag])
            for m, row in res[tag]["models"].items():
                ms = ", ".join(f"{b}: {v:.2f}" for b, v in row["ms"].items())
                print(f"{tag} {m}: set-up {row['setup_s']:.1f} s, {row['graphs']} graphs; ms by batch {ms}", flush=True)
        first = torch.load(saved[tags[0]])
        differ: dict[str, dict] = {}
        for tag in tags[1:]:
            other = torch.load(saved[tag])
            if set(other) != set(first):
                raise RuntimeError(f"{tag} set up {sorted(other)}, {tags[0]} {sorted(first)}: not the same models")
            differ[tag] = {
                m: {
                    str(b): {k: difference(v, other[m][b][k], f"{m} {k} at a batch of {b}") for k, v in out.items()}
                    for b, out in first[m].items()
                }
                for m in first
            }
            print(f"{tag} against {tags[0]}, by model and batch (largest difference; integers: share that differ):")
            for m, rows in differ[tag].items():
                print(f"  {m}: {rows}")
    data = {
        "config": args.config,
        "overrides": args.set,
        "max_batch": args.max_batch,
        "trees": dict(zip(tags, srcs)),
        "results": res,
        "difference": differ,
    }
    print(write_results(args.out, f"compile_batches_{args.device.split(':')[0]}", data))
    return 0


def difference(a: torch.Tensor, b: torch.Tensor, what: str) -> float:
    """A floating output's largest absolute difference; an integer output's share of elements that differ; 0 for
    empty outputs. RuntimeError naming ``what`` if the two are not of one shape and dtype."""
    if a.shape != b.shape or a.dtype != b.dtype:
        raise RuntimeError(f"{what}: {a.dtype}{list(a.shape)} against {b.dtype}{list(b.shape)}")
    if not a.numel():
        return 0.0
    if a.is_floating_point():
        return float((a.double() - b.double()).abs().max())
    return float((a != b).double().mean())


if __name__ == "__main__":
    sys.exit(main())
