"""Build-time planning: every model is built on the meta device (no memory, no weights) to check the pipeline
and to size every mailbox from the declared specs before anything is allocated or spawned."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import torch

from vpengine.config import EngineConfig
from vpengine.models.base import Model, ModelBuildError
from vpengine.models.build import build_model
from vpengine.specs import SpecDict, TensorSpec, format_specs, specs_nbytes

log = logging.getLogger("vpengine.plan")


@dataclass
class Plan:
    cfg: EngineConfig
    frame_spec: SpecDict
    foundation: Model
    heads: dict[str, Model]
    warnings: list[str] = field(default_factory=list)

    @property
    def features(self) -> SpecDict:
        return self.foundation.output_spec

    @property
    def feature_meta(self) -> dict[str, Any]:
        return self.foundation.meta

    def summary(self) -> dict[str, Any]:
        return {
            "frame": {k: str(v) for k, v in self.frame_spec.items()},
            "features": {k: str(v) for k, v in self.features.items()},
            "feature_bytes": specs_nbytes(self.features),
            "heads": {n: {k: str(v) for k, v in m.output_spec.items()} for n, m in self.heads.items()},
        }


def make_plan(cfg: EngineConfig) -> Plan:
    device = torch.device(cfg.device)
    frame_spec = {"frame": TensorSpec((cfg.input.height, cfg.input.width, 3), cfg.input.dtype)}
    fm = build_model(cfg, "foundation", "foundation", frame_spec, {}, device, plan_only=True)
    if fm.input_spec != frame_spec:
        raise ModelBuildError(
            f"foundation model {cfg.foundation_model.model!r} reads {format_specs(fm.input_spec)}, but the input is "
            f"configured as {format_specs(frame_spec)} (input.height/width/dtype)"
        )
    heads: dict[str, Model] = {}
    warnings = []
    for h in cfg.heads:
        model = build_model(cfg, h.name, "head", fm.output_spec, fm.meta, device, plan_only=True)
        for k, spec in model.input_spec.items():
            if k not in fm.output_spec:
                raise ModelBuildError(
                    f"head {h.name!r} ({h.model}) needs feature {k!r} which foundation model "
                    f"{cfg.foundation_model.model!r} does not produce; it produces: {', '.join(fm.output_spec)}"
                )
            if fm.output_spec[k] != spec:
                raise ModelBuildError(
                    f"head {h.name!r} ({h.model}) needs {k!r} as {spec}, but foundation model "
                    f"{cfg.foundation_model.model!r} produces it as {fm.output_spec[k]}"
                )
        trained_on = model.meta.get("trained_on")
        backbone = fm.meta.get("backbone")
        if trained_on and backbone and trained_on != backbone:
            msg = (
                f"head {h.name!r} was trained on backbone {trained_on!r} but the foundation model is {backbone!r}; "
                "its outputs will be degraded"
            )
            warnings.append(msg)
            log.warning(msg)
        heads[h.name] = model
    return Plan(cfg, frame_spec, fm, heads, warnings)
