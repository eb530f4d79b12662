"""Build-time planning: every model is built on the meta device (no memory, no weights) to check the pipeline
and to size every mailbox from the declared specs before anything is allocated or spawned."""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from vpengine.config import EngineConfig
from vpengine.models.base import Model, ModelBuildError
from vpengine.models.build import BuildLockTimeout, build_model
from vpengine.runtime.lanes import Lanes, make_lanes
from vpengine.runtime.supervisor import EngineStartError
from vpengine.specs import SpecDict, TensorSpec, format_specs, specs_nbytes
from vpengine.transport.layout import SlotLayout
from vpengine.transport.memory import free_bytes
from vpengine.transport.ring import ReaderDecl

log = logging.getLogger("vpengine.plan")


@dataclass
class Plan:
    cfg: EngineConfig
    frame_spec: SpecDict
    foundation: Model
    heads: dict[str, Model]
    lanes: Lanes  # Note [Lanes]
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


def make_plan(cfg: EngineConfig, cancelled: Callable[[], bool] | None = None) -> Plan:
    """The engine's plan for ``cfg``: every model built on the meta device, checked against its inputs.

    ``cancelled``: whether the plan is still wanted (a head being added to an engine that stops), checked while a
    build waits for the build lock (Note [One build at a time]); then ``BuildCancelled``.
    """
    try:
        return _make_plan(cfg, cancelled)
    except BuildLockTimeout as e:  # a busy process, not a bad config (Note [One build at a time])
        raise EngineStartError(str(e)) from None


_KINDS_SAID: set[tuple[str, str, tuple[str, ...]]] = set()


def _say_a_kind_without_its_outputs(name: str, model: Model) -> None:
    """Note [Kinds and outputs] in visualize.py: a head whose meta["kind"] names outputs it does not have."""
    from vpengine.visualize import KIND_OUTPUTS, has_kind_outputs

    kind = model.meta.get("kind")
    said = (name, str(kind), tuple(sorted(model.output_spec)))
    if kind in KIND_OUTPUTS and not has_kind_outputs(str(kind), set(model.output_spec)) and said not in _KINDS_SAID:
        _KINDS_SAID.add(said)  # once a process: every plan (an add_head's of the whole config too) builds it again
        log.warning(
            "%s: meta['kind'] is %r, whose pictures and files are made from the outputs %s, but it has %s: it is "
            "drawn and written as a generic head (.npz); name its outputs so, or leave kind out",
            name,
            kind,
            " or ".join(str(sorted(n)) for n in KIND_OUTPUTS[str(kind)]),
            sorted(model.output_spec),
        )


def check_backend_options(cfg: EngineConfig) -> None:
    """Every model's ``backend_options`` as its backend takes them: checked while planning, in the parent, not in
    each worker after the processes started (where a typo came with the worker's traceback). ConfigError naming
    the field, the backend and the keys it takes."""
    from vpengine.backends.options import BackendError, parse_options
    from vpengine.config import ConfigError

    for name in cfg.model_names():
        m = cfg.model(name)
        try:
            parse_options(m.backend, m.backend_options, f"{cfg.model_path(name)}.backend_options")
        except BackendError as e:
            raise ConfigError(str(e)) from None


def _make_plan(cfg: EngineConfig, cancelled: Callable[[], bool] | None) -> Plan:
    check_backend_options(cfg)
    device = torch.device(cfg.device)
    frame_spec = {"frame": TensorSpec((cfg.input.height, cfg.input.width, 3), cfg.input.dtype)}
    fm = build_model(cfg, "foundation", "foundation", frame_spec, {}, device, plan_only=True, cancelled=cancelled)
    if fm.input_spec != frame_spec:
        raise ModelBuildError(
            f"foundation model {cfg.foundation_model.model!r} reads {format_specs(fm.input_spec)}, but the input is "
            f"configured as {format_specs(frame_spec)} (input.height/width/dtype)"
        )
    heads: dict[str, Model] = {}
    warnings: list[str] = []
    refused: list[str] = []
    for h in cfg.heads:
        model = build_model(cfg, h.name, "head", fm.output_spec, fm.meta, device, plan_only=True, cancelled=cancelled)
        _say_a_kind_without_its_outputs(h.name, model)
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
        mismatch = training_mismatch(h.name, model.meta, set(model.input_spec), fm.meta)
        if mismatch and (h.accept_backbone_mismatch or cfg.weights.random_weights):
            msg = f"{mismatch}; its outputs will be degraded"
            warnings.append(msg)
            log.warning(msg)
        elif mismatch:
            refused.append(f"{mismatch}; set accept_backbone_mismatch: true on the head to run it anyway (degraded)")
        heads[h.name] = model
    if refused:
        raise ModelBuildError("\n".join(refused))
    return Plan(cfg, frame_spec, fm, heads, make_lanes(cfg), warnings)


_FEATURE_RE = re.compile(r"^(?:patch|cls)\.(\d+)$")


def training_mismatch(head: str, meta: dict[str, Any], reads: set[str], fm_meta: dict[str, Any]) -> str | None:
    """What differs between the features a head was trained on and those it would read here, naming both sides;
    None when nothing does (or when the head or the backbone does not say).

    Note [Trained layers]: a released head was trained on its backbone recipe's default feature blocks
    (``default_layers`` in the foundation model's meta), so ``foundation_model.options.layers`` moves a head that
    reads ``patch.i`` / ``cls.i`` to another block even though the backbone's name is the same. Only the blocks a
    head reads count: a linear head reading ``patch.3`` does not care where ``patch.0`` comes from.
    """
    trained_on, backbone = meta.get("trained_on"), fm_meta.get("backbone")
    if not trained_on or not backbone:
        return None
    if trained_on != backbone:
        return f"head {head!r} was trained on backbone {trained_on!r} but the foundation model is {backbone!r}"
    layers, default = fm_meta.get("layers"), fm_meta.get("default_layers")
    if layers is None or default is None:
        return None
    indices = sorted({int(m.group(1)) for k in reads if (m := _FEATURE_RE.match(k))})
    moved = [i for i in indices if i < len(layers) and layers[i] != default[i]]
    if not moved:
        return None
    what = ", ".join(f"feature {i} from block {layers[i]} instead of block {default[i]}" for i in moved)
    return (
        f"head {head!r} would read {what}: it was trained on {trained_on!r} with layers {list(default)}, but "
        f"foundation_model.options.layers is {list(layers)}"
    )


# ------------------------------------------------------------------------------------------------ mailboxes
#: Results of each head a caller may hold without a copy, each keeping one output slot (Note [Borrowed results] in
#: engine/results.py, whose lease readers these are).
LEASES = 2
#: Frames a fifo reader may fall behind and still catch up: its mailbox gets this many slots more.
FIFO_MARGIN = 4


def mailboxes(plan: Plan, shared: bool) -> list[dict[str, Any]]:
    """``SlotRing.create``'s arguments for every mailbox: the input, the features, one output per head. Each is as
    small as its readers allow (readers + tags + 1: Note [Slot lifetime], Note [Tagged slots] in
    transport/ring.py), plus a slot a camera more being written in the input and the features (the cameras' threads
    fill theirs at once; the foundation fills its batch's before it publishes), plus the margin a fifo reader needs to
    catch up, plus the leases of each head's output.
    With several cameras, every slot is tagged with its frame's camera and each model reads with one reader per
    camera it serves (its lanes, Note [Lanes]); results are read untagged, every camera's in one stream."""
    cfg, lanes = plan.cfg, plan.lanes
    device = torch.device(cfg.device)
    gpu = device.type == "cuda"  # host rings a GPU copies from or to are page-locked
    tags = len(lanes.cameras)

    def readers(model: str, mode: str) -> list[ReaderDecl]:
        return [
            ReaderDecl(lane.reader, mode, tag=lane.reader_tag)  # type: ignore[arg-type]
            for lane in lanes.of(model)
        ]

    fifo_fm = FIFO_MARGIN if cfg.foundation_model.input_mode == "fifo" else 0
    fifo_heads = FIFO_MARGIN if any(h.input_mode == "fifo" for h in cfg.heads) else 0
    feature_readers = [r for h in cfg.heads for r in readers(h.name, h.input_mode)]
    # the seats of heads added at run time: inactive until a head takes one (Note [Heads at run time])
    feature_readers += [
        ReaderDecl(lane.reader, "latest", active=False, tag=lane.reader_tag)
        for seat in lanes.seats
        for lane in lanes.seat_lanes(seat)
    ]
    boxes: list[dict[str, Any]] = [
        dict(
            name="input",
            specs=plan.frame_spec,
            # a camera's reader's, its newest, the one its thread fills (Note [Frames of several cameras at once]
            # in engine/core.py)
            n_slots=3 * tags + fifo_fm * tags,
            readers=readers("foundation", cfg.foundation_model.input_mode),
            device="cpu",
            shared=shared,
            pinned=gpu,
            n_tags=tags,
        ),
        dict(
            name="features",
            specs=plan.features,
            # the foundation fills a slot per camera of its batch before it publishes them (Note [Tagged slots])
            n_slots=max(3, len(feature_readers) + 2 * tags + fifo_heads * tags),
            readers=feature_readers,
            device=device,
            shared=shared,
            n_tags=tags,
        ),
    ]
    for h in cfg.heads:
        leases = [ReaderDecl(f"lease{i}", active=False) for i in range(LEASES)]
        boxes.append(
            dict(
                name=f"out.{h.name}",
                specs=plan.heads[h.name].output_spec,
                # kept for results(): output.slots a camera, plus the leases (and room for each camera's newest)
                n_slots=h.output.slots * len(lanes.of(h.name)) + LEASES + tags - 1,
                readers=[ReaderDecl("results", "fifo", active=False), ReaderDecl("peek"), *leases],
                device=device if h.output.location == "device" else "cpu",
                shared=shared,
                overflow=h.output.overflow,
                pinned=gpu,
                n_tags=tags,
            )
        )
    return boxes


def check_preallocation(boxes: list[dict[str, Any]]) -> None:
    """Refuse mailboxes that do not fit the memory free now, naming their size (rather than failing in the middle
    of allocating them, or leaving the machine swapping)."""
    need: dict[str, dict[str, int]] = {}  # device -> mailbox -> bytes
    for m in boxes:
        nbytes = SlotLayout.from_specs(m["specs"], m["n_slots"]).total_bytes
        need.setdefault(str(torch.device(m["device"])), {})[m["name"]] = nbytes

    def size(b: float) -> str:
        return f"{b / 1e9:.2f} GB" if b >= 1e9 else f"{b / 1e6:.1f} MB"

    for dev, sizes in need.items():
        total, free = sum(sizes.values()), free_bytes(torch.device(dev))
        if free is not None and total > free:
            biggest = ", ".join(f"{n} {size(b)}" for n, b in sorted(sizes.items(), key=lambda x: -x[1])[:3])
            raise EngineStartError(
                f"the mailboxes need {size(total)} of {'host' if dev == 'cpu' else dev} memory ({biggest}), "
                f"but only {size(free)} is free; lower input.height/width, output.slots or the number of heads"
            )
