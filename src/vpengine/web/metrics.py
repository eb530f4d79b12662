"""``/metrics``: an engine's ``stats()`` in the Prometheus text format, through ``prometheus-client``.

Read at scrape time from the control block (nothing is recorded between scrapes, so an unscraped engine pays
nothing). Every series is ``vpengine_*`` with a ``model`` label (``foundation`` or a head name):

* counters: ``runs``, ``skipped`` (frames a model never saw), ``dropped``, ``errors``, ``restarts``; per head
  ``results_missed`` (results nobody collected in time); engine ``frames_submitted`` and ``frames_rejected``;
* gauges: ``achieved_hz`` (over the last 2 s), ``target_hz`` (``+Inf`` unlimited, 0 paused), ``device_memory_bytes``
  (the worker's reserved device memory), ``mailbox_bytes`` by ``location``, ``up`` (1 while the engine runs);
* summaries: ``latency_seconds`` (a run's model time) and ``e2e_latency_seconds`` (submit to output), quantiles
  0.5, 0.9 and 0.99 over each model's last 512 runs, ``_count`` = runs. There is no ``_sum``: the engine keeps
  the recent window, not a running total, and a made-up sum would mislead ``rate(_sum) / rate(_count)``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric, SummaryMetricFamily

if TYPE_CHECKING:
    from vpengine.engine import Engine

_COUNTERS = {
    "runs": "Runs of the model.",
    "skipped": "Input frames the model never saw (a newer frame replaced them, or the rate limit skipped them).",
    "dropped": "Outputs dropped by a full output mailbox.",
    "errors": "Runs that raised an error.",
    "restarts": "Restarts of the model's worker after a crash or hang.",
}
_QUANTILES = {"0.5": "p50", "0.9": "p90", "0.99": "p99"}


def _finite(v: Any) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


class EngineCollector:
    """A prometheus-client collector over ``engine()`` (an Engine, or None while there is none)."""

    def __init__(self, engine: Callable[[], Engine | None]) -> None:
        self._engine = engine

    def collect(self) -> Iterator[Metric]:
        eng = self._engine()
        stats: dict[str, Any] = eng.stats() if eng is not None else {"engine": {"state": "none"}}
        up = GaugeMetricFamily("vpengine_up", "1 while the engine runs, else 0.")
        up.add_metric([], 1.0 if stats["engine"]["state"] == "running" else 0.0)
        yield up
        if "models" not in stats:
            return
        models: dict[str, dict[str, Any]] = stats["models"]
        for field, doc in _COUNTERS.items():
            c = CounterMetricFamily(f"vpengine_{field}", doc, labels=["model"])
            for name, m in models.items():
                c.add_metric([name], m[field])
            yield c
        gauges = {
            "achieved_hz": ("Runs per second over the last 2 s.", lambda m: m["achieved_hz"]),
            "target_hz": (
                "Rate limit: +Inf unlimited, 0 paused.",
                lambda m: math.inf if m["target_hz"] is None else m["target_hz"],
            ),
            "device_memory_bytes": (
                "Device memory of the model (its process's when it has one to itself).",
                lambda m: m["device_mem_bytes"],
            ),
        }
        for field, (doc, get) in gauges.items():
            g = GaugeMetricFamily(f"vpengine_{field}", doc, labels=["model"])
            for name, m in models.items():
                g.add_metric([name], get(m))
            yield g
        for field, doc in (
            ("latency", "Model time of a run, over the last 512 runs."),
            ("e2e_latency", "Submit to output, over the last 512 runs."),
        ):
            name = f"vpengine_{field}_seconds"
            s = SummaryMetricFamily(name, doc, labels=["model"])
            for model, m in models.items():
                for q, key in _QUANTILES.items():
                    v = _finite(m[f"{field}_ms"][key])
                    if v is not None:
                        s.add_sample(name, {"model": model, "quantile": q}, v / 1e3)
                s.add_sample(f"{name}_count", {"model": model}, m["runs"])
            yield s
        missed = CounterMetricFamily(
            "vpengine_results_missed", "Results overwritten before the result stream took them.", labels=["model"]
        )
        for head, r in stats.get("results", {}).items():
            missed.add_metric([head], r["missed"])
        yield missed
        engine = stats["engine"]
        for field, doc in (("submitted", "Frames submitted."), ("rejected", "Frames rejected at submit.")):
            c = CounterMetricFamily(f"vpengine_frames_{field}", doc)
            c.add_metric([], engine[field])
            yield c
        mem = stats.get("memory") or {}
        g = GaugeMetricFamily("vpengine_mailbox_bytes", "Mailbox memory allocated at start.", labels=["location"])
        g.add_metric(["host"], mem.get("mailbox_host_bytes", 0))
        g.add_metric(["device"], mem.get("mailbox_device_bytes", 0))
        yield g


def registry(engine: Callable[[], Engine | None]) -> CollectorRegistry:
    """A registry of its own (not prometheus-client's global one) holding an :class:`EngineCollector`."""
    reg = CollectorRegistry(auto_describe=False)
    reg.register(EngineCollector(engine))
    return reg
