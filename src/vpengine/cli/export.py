"""``vpengine export``: one model of a config to ONNX, checked, and verified against PyTorch.

``--model`` is ``foundation`` (preprocessing + backbone: uint8 frame in, features out) or a head name (features in,
the head's outputs out). Graph inputs and outputs carry the model's spec names and dtypes, and its per-frame shapes
behind a batch dimension of 1 (``[1, *shape]``; the manifest's ``batch``). The file is
written to ``OUT/NAME.onnx`` with ``OUT/NAME.json`` beside it (specs, precision, opset, model metadata and the
verification result): what a TensorRT build or another runtime needs to wire the model up.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from vpengine.arguments import add_overrides_argument


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", "-c", required=True, help="engine config (YAML or JSON)")
    p.add_argument("--model", "-m", required=True, help="'foundation' or a head name of the config")
    p.add_argument("--out", "-o", required=True, help="output folder for NAME.onnx and NAME.json")
    p.add_argument(
        "--precision",
        choices=["fp32", "fp16"],
        help="export precision (default: the model's precision in the config); bf16 has no ONNX kernels",
    )
    p.add_argument("--opset", type=int, default=18, help="ONNX opset, 17..23 (default 18)")
    p.add_argument(
        "--exporter",
        choices=["auto", "dynamo", "torchscript"],
        default="auto",
        help="torch.onnx exporter (auto: what the model asks for; torchscript for Faster R-CNN)",
    )
    add_overrides_argument(p, "input.height=720")
    p.add_argument("--random-weights", action="store_true", help="use random weights (loudly) instead of checkpoints")
    p.add_argument("--no-verify", action="store_true", help="skip running the export on ONNX Runtime against PyTorch")


def _jsonable(v: Any) -> Any:
    return json.loads(json.dumps(v, default=str))


def export_model(
    config: Any,
    name: str,
    out_dir: str | Path,
    precision: str | None = None,
    opset: int = 18,
    exporter: str = "auto",
    verify: bool = True,
) -> dict[str, Any]:
    """Export model ``name`` ("foundation" or a head) of ``config`` to ``out_dir/name.onnx``; return its manifest."""
    import torch

    from vpengine.backends.onnx_export import check_onnx_precision, export_onnx, resolve_exporter
    from vpengine.backends.options import parse_options
    from vpengine.config import load_config
    from vpengine.models.build import build_model
    from vpengine.runtime.plan import make_plan

    cfg = load_config(config)
    names = cfg.model_names()
    if name not in names:
        raise ValueError(f"--model {name!r} is not a model of this config; accepted: {', '.join(names)}")
    try:  # before the export, not a traceback after it: a file in the way, a folder that cannot be written
        Path(out_dir).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(f"--out {str(out_dir)!r}: cannot make the folder for NAME.onnx: {e.strerror or e}") from None
    if precision is not None:
        where = cfg.model_path(name)
        cfg = load_config(cfg, [f"{where}.precision={precision}"])
    precision = cfg.model(name).precision or cfg.precision
    check_onnx_precision(precision, name)
    parse_options("onnx", {"opset": opset, "exporter": exporter}, name)
    plan = make_plan(cfg)
    cpu = torch.device("cpu")
    if name == "foundation":
        model = build_model(cfg, name, "foundation", plan.frame_spec, {}, cpu, plan_only=False)
    else:
        model = build_model(cfg, name, "head", plan.features, plan.feature_meta, cpu, plan_only=False)
    exporter = resolve_exporter(exporter, model)
    out = Path(out_dir)
    path = out / f"{name}.onnx"
    result = export_onnx(model, path, precision, opset, exporter, name, verify=verify)
    manifest: dict[str, Any] = {
        "model": name,
        "recipe": cfg.model(name).model,
        "file": path.name,
        "precision": precision,
        "opset": opset,
        "exporter": exporter,
        "batch": 1,  # graph shapes are [batch, *the per-frame shapes below]
        "inputs": {k: s.to_json() for k, s in model.input_spec.items()},
        "outputs": {k: s.to_json() for k, s in model.output_spec.items()},
        "meta": _jsonable(model.meta),
        "export_s": round(result["export_s"], 3),
        "verification": result["verification"],
        "created": time.time(),
        "torch": torch.__version__,
    }
    (out / f"{name}.json").write_text(json.dumps(manifest, indent=1))
    return manifest


def main(args: argparse.Namespace) -> int:
    from vpengine.backends.onnx_export import describe_check
    from vpengine.config import load_config
    from vpengine.specs import TensorSpec, format_specs

    overrides = list(args.overrides)
    if args.random_weights:
        overrides.append("weights.random_weights=true")
    cfg = load_config(args.config, overrides)
    m = export_model(cfg, args.model, args.out, args.precision, args.opset, args.exporter, not args.no_verify)
    path = Path(args.out) / m["file"]
    size = sum(p.stat().st_size for p in path.parent.glob(f"{path.name}*")) / 1e6

    def specs(d: dict[str, Any]) -> str:
        return format_specs({k: TensorSpec(tuple(v["shape"]), v["dtype"]) for k, v in d.items()})

    print(f"{args.model} -> {path} ({size:.1f} MB, {m['precision']}, opset {m['opset']}, {m['export_s']:.1f} s)")
    print(f"  inputs:  {specs(m['inputs'])}")
    print(f"  outputs: {specs(m['outputs'])}")
    v = m["verification"]
    if v is not None:
        print(f"  verified on {v['runtime']} against PyTorch, {v['inputs']} inputs:")
        for k, r in v["outputs"].items():
            print(f"    {k}: {describe_check(r)}")
    return 0
