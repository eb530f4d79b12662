"""What a pipeline counts of its results (:class:`Tally`) and the summary it makes of a run (:func:`summarize`):
per model, per head's results and, with several cameras, per camera."""

from __future__ import annotations

import collections
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from vpengine.engine.results import Result
    from vpengine.pipeline.run import Pipeline


@dataclass
class Tally:
    """The results a pipeline received, their end-to-end latencies and those not written, per (camera, head)."""

    latencies: collections.defaultdict[tuple[str, str], list[float]] = field(
        default_factory=lambda: collections.defaultdict(list)
    )
    received: collections.Counter[tuple[str, str]] = field(default_factory=collections.Counter)
    unwritten: collections.Counter[tuple[str, str]] = field(default_factory=collections.Counter)

    def add(self, result: Result) -> tuple[str, str]:
        key = (result.camera, result.head)
        self.received[key] += 1
        self.latencies[key].append(result.latency)
        return key

    def of(self, cameras: list[str], head: str) -> dict[str, Any]:
        """A head's results over ``cameras``: end-to-end latency percentiles and how many came."""
        return {
            "e2e_latency_ms": percentiles([x for c in cameras for x in self.latencies[(c, head)]]),
            "results_received": sum(self.received[(c, head)] for c in cameras),
        }


def percentiles(values: list[float]) -> dict[str, float | None]:
    """p50, p99 and mean in milliseconds of ``values`` in seconds (None for each when there are none)."""
    if not values:
        return {"p50": None, "p99": None, "mean": None}
    a = np.asarray(values) * 1e3
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)), "mean": float(a.mean())}


def _model_entry(m: dict[str, Any], wall: float, results: Mapping[str, Any] | None = None) -> dict[str, Any]:
    return {
        "target_hz": m["target_hz"],
        "achieved_hz": m["runs"] / wall if wall > 0 else 0.0,
        "runs": m["runs"],
        "skipped": m["skipped"],
        "dropped": m["dropped"],
        "errors": m["errors"],
        "restarts": m["restarts"],
        "latency_ms": {"p50": m["latency_ms"]["p50"], "p99": m["latency_ms"]["p99"]},
        **(results or {}),
    }


def summarize(pipe: Pipeline, interrupted: bool, wall: float, stats: dict[str, Any]) -> dict[str, Any]:
    """The summary of a run of ``pipe`` that took ``wall`` seconds and ended with the engine's ``stats``."""
    tally, heads, served = pipe.tally, pipe.heads, pipe.served
    models = {}
    for name, m in stats["models"].items():
        extra = None
        if name in heads:
            extra = {
                **tally.of(list(served), name),
                "results_missed": stats["results"][name]["missed"],
                "results_unwritten": pipe.writer.unwritten[name],
            }
        models[name] = _model_entry(m, wall, extra)
    sources = pipe.sources
    submitted = sum(f.submitted for f in pipe.feeds)
    summary: dict[str, Any] = {
        "config": pipe.config.name,
        # the config as it ran, --set overrides and the CLI's own (cameras, mode, device) applied: `vpengine run -c`
        # takes this back (a file holding it) to run the same engine again
        "config_used": pipe.config.model_dump(mode="json"),
        "source": ", ".join(s.describe() if c is None else f"{c}={s.describe()}" for c, s in sources.items()),
        "pace": pipe.pace,
        "in_flight": pipe.in_flight,  # lockstep: rounds of frames at once (Note [Frames in flight])
        "frames_submitted": submitted,
        "source_missed": sum(s.missed for s in sources.values()),
        "inputs_skipped": [x for s in sources.values() for x in s.skipped],
        "inputs_partial": [x for s in sources.values() for x in s.partial],
        "interrupted": interrupted,
        "wall_s": wall,
        "input_hz": submitted / wall if wall > 0 else 0.0,
        "mode": pipe.config.mode,
        "device": pipe.config.device,
        "models": models,
        "warnings": pipe.engine.plan.warnings,
    }
    if len(served) > 1:  # each camera's frames and models, from stats()["cameras"] (Note [Cameras] in worker.py)
        by_camera = {f.camera: f for f in pipe.feeds}
        summary["cameras"] = {
            c: {
                "source": by_camera[c].source.describe(),
                "frames_submitted": by_camera[c].submitted,
                "source_missed": by_camera[c].source.missed,
                "models": {
                    name: {
                        **_model_entry(
                            m,
                            wall,
                            {**tally.of([c], name), "results_unwritten": tally.unwritten[(c, name)]}
                            if name in heads
                            else None,
                        ),
                        "entry": m["entry"],
                        "late": m.get("late", 0),
                        "deferred": m.get("deferred", 0),
                    }
                    for name, m in stats["cameras"].get(c, {}).items()
                },
            }
            for c in served
        }
    return summary


def write_summary(out_dir: str | Path, summary: dict[str, Any]) -> None:
    """``out_dir/summary.json`` (made with its folder): valid JSON, so numbers that are not finite (a latency of no
    run is NaN) become null and numpy's numbers plain ones."""
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    text = json.dumps(_plain(summary), indent=2, allow_nan=False, default=str)
    (Path(out_dir) / "summary.json").write_text(text)


def _plain(o: Any) -> Any:
    """``o`` with its floats finite or None and numpy scalars as Python's (``json.dumps`` writes NaN otherwise, and a
    numpy float is a float to it)."""
    if isinstance(o, dict):
        return {k: _plain(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_plain(v) for v in o]
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, (int, np.integer)):
        return int(o)
    if isinstance(o, (float, np.floating)):
        return float(o) if math.isfinite(o) else None
    return o
