"""Parameter accounting: how many parameters each model of a config has, and what sharing the backbone saves.

Every model is built on the meta device (``build_model(..., plan_only=True)``), so counting costs no memory and
loads no weights, even for ViT-g. The saving compares the engine's layout, one foundation model whose features every head
reads, with the naive one where each of the N heads runs its own copy of the backbone::

    shared      = F + sum(H_i)
    independent = N * F + sum(H_i)          (= shared when N <= 1)
    saved       = independent - shared = (N - 1) * F
    percent     = 100 * saved / independent

Parameters are counted once per tensor (tied weights count once); buffers (e.g. BatchNorm statistics) are reported
separately because they are state, not learned weights.
"""

from __future__ import annotations

from typing import Any

from torch import nn


def count_parameters(module: nn.Module) -> dict[str, int]:
    """Parameters, their bytes at the dtype they were built in, and buffer elements of ``module``."""
    params = list(module.parameters())  # parameters() already yields a tied tensor once
    return {
        "params": sum(p.numel() for p in params),
        "param_bytes": sum(p.numel() * p.element_size() for p in params),
        "buffers": sum(b.numel() for b in module.buffers()),
    }


def sharing_saving(foundation_params: int, head_params: list[int]) -> dict[str, Any]:
    """Totals for one shared foundation model versus one backbone copy per head (see the module docstring)."""
    n = len(head_params)
    heads = sum(head_params)
    shared = foundation_params + heads
    independent = max(n, 1) * foundation_params + heads
    saved = independent - shared
    return {
        "heads": n,
        "shared_total": shared,
        "independent_total": independent,
        "saved": saved,
        "percent_fewer": 100.0 * saved / independent if independent else 0.0,
    }


def parameter_report(cfg: Any) -> dict[str, Any]:
    """Parameters per model of an engine config and the saving of the shared backbone.

    ``cfg`` is an :class:`~vpengine.config.EngineConfig` or anything ``load_config`` accepts (path, dict).
    Returns ``{"config", "models": {name: {recipe, role, params, param_bytes, buffers}}, "foundation",
    "sharing": {heads, shared_total, independent_total, saved, percent_fewer}}``.
    """
    import torch

    from vpengine.config import load_config
    from vpengine.models.build import build_model, frame_spec

    cfg = load_config(cfg)
    device = torch.device(cfg.device)
    fm = build_model(cfg, "foundation", "foundation", frame_spec(cfg), {}, device, plan_only=True)
    models: dict[str, dict[str, Any]] = {
        "foundation": {"recipe": cfg.foundation_model.model, "role": "foundation", **count_parameters(fm)}
    }
    for h in cfg.heads:
        head = build_model(cfg, h.name, "head", fm.output_spec, fm.meta, device, plan_only=True)
        models[h.name] = {"recipe": h.model, "role": "head", **count_parameters(head)}
    heads = [m["params"] for m in models.values() if m["role"] == "head"]
    return {
        "config": cfg.name,
        "foundation": cfg.foundation_model.model,
        "models": models,
        "sharing": sharing_saving(models["foundation"]["params"], heads),
    }


def _short(n: int) -> str:
    for div, unit in ((1e9, "B"), (1e6, "M"), (1e3, "k")):
        if n >= div:
            return f"{n / div:.1f}{unit}"
    return str(n)


def format_report(report: dict[str, Any]) -> str:
    """The report as the text table ``vpengine info --models`` prints."""
    models = report["models"]
    w = max(10, *(len(n) for n in models))
    rw = max(8, *(len(m["recipe"]) for m in models.values()))
    lines = [
        f"parameters per model (config {report['config']!r})",
        f"  {'model':{w}s}  {'recipe':{rw}s}  {'role':10s}  {'parameters':>15s}  {'':>7s}  {'MiB':>9s}",
    ]
    for name, m in models.items():
        lines.append(
            f"  {name:{w}s}  {m['recipe']:{rw}s}  {m['role']:10s}  {m['params']:>15,d}  {_short(m['params']):>7s}"
            f"  {m['param_bytes'] / 2**20:9.1f}"
        )
    s = report["sharing"]
    heads = f"{s['heads']} head" + ("" if s["heads"] == 1 else "s")
    rows = [
        (f"one shared {report['foundation']} + {heads}:", s["shared_total"]),
        (f"{heads}, each with its own backbone copy:", s["independent_total"]),
    ]
    lw = max(len(label) for label, _ in rows)
    lines.append("")
    lines.extend(f"{label:{lw}s}  {n:>15,d}  ({_short(n)})" for label, n in rows)
    lines.append(
        f"sharing the backbone saves {s['saved']:,d} parameters ({_short(s['saved'])}): {s['percent_fewer']:.1f}% fewer"
    )
    return "\n".join(lines)
