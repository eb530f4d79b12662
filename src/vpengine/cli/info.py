"""``vpengine info``: what this machine offers the engine."""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import platform
import sys
from typing import Any

from vpengine.arguments import add_overrides_argument

#: What ``info --models`` accounts for without ``--config``
MODELS_DEFAULT = "dinov2s_depth_seg_det"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    # --models: parameter accounting of a config (models/accounting.py)
    p.add_argument(
        "--models",
        action="store_true",
        help="parameters per model of a config and what sharing the backbone saves (instead of the machine info)",
    )
    p.add_argument(
        "--config",
        "-c",
        help=f"engine config for --models, which it implies (default: {MODELS_DEFAULT}, the shipped GPU config: "
        "backbone and 3 heads)",
    )
    add_overrides_argument(p, "foundation_model.model=dinov2_vitb14", "a config field for --models")


def _version(dist: str) -> str | None:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def collect() -> dict[str, Any]:
    import torch

    from vpengine import __version__
    from vpengine.runtime import mps

    versions = {"vpengine": __version__, "python": platform.python_version()}
    for dist in (
        "torch",
        "torchvision",
        "timm",
        "numpy",
        "opencv-python-headless",
        "onnxruntime",
        "onnx",
        "cyclonedds",
        "rosbags",
        "transformers",
        "cuda-bindings",
        "triton",
    ):
        versions[dist] = _version(dist)
    devices: list[dict[str, Any]] = [
        {"device": "cpu", "name": platform.processor() or platform.machine(), "cores": os.cpu_count()}
    ]
    cuda: dict[str, Any] = {"available": torch.cuda.is_available(), "torch_cuda": torch.version.cuda}
    if torch.cuda.is_available():
        for i in range(torch.cuda.device_count()):
            prop = torch.cuda.get_device_properties(i)
            devices.append(
                {
                    "device": f"cuda:{i}",
                    "name": prop.name,
                    "memory_gb": round(prop.total_memory / 2**30, 1),
                    "compute_capability": f"{prop.major}.{prop.minor}",
                    "multiprocessors": prop.multi_processor_count,
                }
            )
    return {
        "versions": versions,
        "platform": platform.platform(),
        "devices": devices,
        "cuda": cuda,
        "mps": mps.status(),
        "kernels": {"fused_upsample_argmax": _fused_upsample_argmax()},
    }


def _fused_upsample_argmax() -> str:
    """Whether the linear seg head's ``upsample: auto`` runs its Triton kernel here (Note [Fused upsample + argmax])."""
    import torch

    from vpengine.models.upsample_argmax import fused_unavailable

    why_not = (
        fused_unavailable(torch.device("cuda", torch.cuda.current_device()))
        if torch.cuda.is_available()
        else "no CUDA device visible"
    )
    return "available" if why_not is None else f"not used: {why_not} (PyTorch's interpolate and argmax run instead)"


def models_main(args: argparse.Namespace) -> int:
    """``vpengine info --models``: parameter accounting, every model built on the meta device."""
    from vpengine.config import load_config
    from vpengine.models.accounting import format_report, parameter_report

    # without a config, the shipped one of backbone and heads: the built-in defaults have no head to account for
    report = parameter_report(load_config(args.config or MODELS_DEFAULT, args.overrides))
    print(json.dumps(report, indent=2) if args.json else format_report(report))
    return 0


def main(args: argparse.Namespace) -> int:
    # a config or an override is for the parameter accounting: given, it is asked for (not ignored)
    if getattr(args, "models", False) or args.config or args.overrides:
        return models_main(args)
    info = collect()
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    w = sys.stdout.write
    w(f"vpengine {info['versions']['vpengine']} on {info['platform']}\n\nversions:\n")
    for k, v in info["versions"].items():
        w(f"  {k:24s} {v or '-'}\n")
    w("\ndevices:\n")
    for d in info["devices"]:
        w("  " + ", ".join(f"{k}={v}" for k, v in d.items()) + "\n")
    if not info["cuda"]["available"]:
        w(f"  (no CUDA device visible; torch built with CUDA {info['cuda']['torch_cuda'] or 'none'})\n")
    m = info["mps"]
    w(
        f"\nCUDA MPS: {'daemon reachable' if m['reachable'] else 'not reachable'} at {m['pipe_directory']}"
        f"{'' if m['reachable'] else ' (' + m['reason'] + ')'}\n"
    )
    w(f"seg heads' fused upsample + argmax: {info['kernels']['fused_upsample_argmax']}\n")
    return 0
