"""Typed, validated engine configuration, written by users as YAML or JSON.

Every model has its own block (model name, checkpoint, options, rate, backend, precision); the engine block sets
mode, device and the mailboxes. Unknown keys and bad values fail with the field's dotted path, the value given and
what is accepted. Command lines override any field with dotted paths: ``heads.depth.rate_hz=5`` (a head may be named
by its ``name`` or its index).
"""

from __future__ import annotations

import difflib
import json
import re
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from vpengine import checks

Precision = Literal["fp32", "fp16", "bf16"]
#: The one camera of an engine that configures none.
DEFAULT_CAMERA = "camera"
MAX_CAMERAS = 16
Priority = Annotated[int, Field(ge=checks.MIN_PRIORITY, le=checks.MAX_PRIORITY)]  # higher: more important
_GIVE_WAY = (
    "Higher: more important. When the device cannot serve every rate, lower lanes are throttled (runs skipped, counted) "
    "so higher ones keep rate and deadline; equals never throttle each other (Note [Give way] in runtime/governor.py)."
)
Backend = Literal["eager", "compile", "onnx"]
NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_\-]{0,63}$")
_DEVICE_RE = re.compile(r"^(cpu|cuda(:\d+)?)$")


class ConfigError(ValueError):
    """A configuration that cannot be used; the message names the field, the value and what is accepted."""


class _Strict(BaseModel):
    # NaN and infinity are refused in every number field: a NaN normalisation ruins every output, an infinite
    # timeout makes stop() unbounded.
    model_config = ConfigDict(extra="forbid", validate_assignment=True, protected_namespaces=(), allow_inf_nan=False)


class InputConfig(_Strict):
    """The camera frames given to ``Engine.submit``."""

    height: int = Field(
        480,
        ge=14,
        le=16384,
        description="Height in pixels the models run at (their mailboxes and graphs are this size). Frames of any "
        "other size are scaled into it with their aspect ratio kept, and their outputs come back at their own size "
        "(Note [Frame grid] in engine/boundary.py); set it to your camera's to spare that resizing.",
    )
    width: int = Field(640, ge=14, le=16384, description="Width in pixels the models run at (see height).")
    max_frame_side: int = Field(
        8192, ge=14, le=65536, description="Largest frame height or width accepted; larger frames are refused."
    )
    color: Literal["bgr", "rgb"] = Field("bgr", description="Channel order of submitted frames (OpenCV gives BGR).")
    dtype: Literal["uint8", "float32"] = Field(
        "uint8",
        description="Pixel type: uint8 0..255, or float32 0..1 (submit refuses NaN, inf and values past 2, a /255 "
        "forgotten; a frame_slot's frame, written in place, is not checked). The CLI and ROS 2 take their sources' "
        "uint8 frames whatever it says.",
    )


class PreprocessConfig(_Strict):
    """How frames become the foundation model's input, on the model's device."""

    resize: Literal["aspect", "square", "none"] = Field(
        "aspect",
        description="aspect: short side to `size`, long side scaled and rounded to the patch multiple (1920x1080 -> "
        "924x518); square: `size` x `size` (the paper's setting, distorts the image); none: crop to the patch multiple.",
    )
    size: int = Field(518, ge=14, le=8192, description="Target short side (aspect) or side (square) in pixels.")


class ModelConfig(_Strict):
    """Fields common to the foundation model and every head."""

    model: str = Field(..., description="Model recipe name from the catalog, or 'package.module:Class'.")
    checkpoint: str | None = Field(
        None, description="Checkpoint file path or catalog weight name; null: the recipe's default weights."
    )
    options: dict[str, Any] = Field(default_factory=dict, description="Recipe options (validated by the recipe).")
    rate_hz: float | None = Field(
        None,
        description="Rate limit in Hz; null: as fast as new data arrives; 0: paused. Changeable at run time.",
    )
    backend: Backend = Field("eager", description="Execution backend: eager PyTorch, torch.compile, ONNX Runtime.")
    backend_options: dict[str, Any] = Field(
        default_factory=dict,
        description="Options of the backend (validated by it, see vpengine/backends/options.py), e.g. compile: "
        "{mode: max-autotune, cudagraphs: true}; onnx: {opset: 18, providers: [CUDAExecutionProvider]}.",
    )
    precision: Precision | None = Field(None, description="fp32 | fp16 | bf16; null: the engine's precision.")

    cpu_threads: int = Field(
        1,
        ge=1,
        le=256,
        description="PyTorch intra-op threads in this model's worker process (CPU). In thread mode the models share "
        "one process and so one pool, sized by the foundation model's value; the heads' values are not used.",
    )
    process: str | None = Field(
        None,
        pattern=r"^[A-Za-z0-9_.-]{1,64}$",
        description="Process mode: models naming the same process share one worker process, each on its own "
        "thread and CUDA stream: one CUDA context instead of one each (several hundred MB of device memory per "
        "process), but a crash or hang of one restarts all of them. null: a process of its own. Thread mode: "
        "unused (every model is in the engine's process).",
    )
    mps_priority: Literal["normal", "below_normal"] | None = Field(
        None,
        description="CUDA MPS client priority of this model's process (CUDA_MPS_CLIENT_PRIORITY); null: below_normal "
        "for a head less important than the engine's most important head, else normal.",
    )

    input_mode: Literal["latest", "fifo"] = Field(
        "latest",
        description="How the model reads its input (frames for the foundation model, features for a head). latest: after "
        "falling behind it takes the newest and skips the ones in between (counted) -- the lowest latency, for control "
        "loops. fifo: it takes every one in order and catches up, absorbing a lag of up to 4 frames (its mailbox is "
        "sized for that) before the oldest are skipped (counted) -- for recording and bridges where every frame should come out. A rate limit still applies: a fifo "
        "model then runs on ever older frames until they are overwritten.",
    )

    @field_validator("rate_hz", mode="before")
    @classmethod
    def _rate(cls, v: Any) -> float | None:
        # before pydantic's coercion: the same values as every other door, spelled as a config writes them (null)
        return checks.rate(None, v, spell=lambda x: json.dumps(x, default=str))  # a YAML date is no JSON


class FoundationModelConfig(ModelConfig):
    """The backbone that runs once per frame; its features go to every head."""

    model: str = Field("dinov2_vits14", description="Backbone recipe name.")
    preprocess: PreprocessConfig = Field(default_factory=PreprocessConfig)  # type: ignore[arg-type]


class OutputConfig(_Strict):
    """A head's output mailbox, read by ``Engine.latest/results/wait`` and the sinks."""

    slots: int = Field(
        4,
        ge=4,
        le=256,
        description="Results of this head kept for Engine.results (>= 4): how far a reader may fall behind before the "
        "oldest unread are overwritten (counted).",
    )
    overflow: Literal["drop_oldest", "drop_newest", "block"] = Field(
        "drop_oldest",
        description="When results() falls behind: overwrite the oldest unread (counted), drop the newest "
        "(counted), or make the head wait.",
    )
    location: Literal["host", "device"] = Field(
        "host",
        description="host: results land in shared host memory; device: stay on the GPU for GPU consumers.",
    )
    grid: Literal["frame", "native"] = Field(
        "frame",
        description="frame: outputs in the submitted frame's pixel grid (maps at its size, boxes in its pixels); "
        "native: as the head computed them, in the grid of input.height x width (Result.grid says which).",
    )


class CameraConfig(_Strict):
    """One of several cameras feeding the engine (Note [Cameras] in runtime/worker.py)."""

    name: str = Field(..., description="Unique camera name (letters, digits, _ and -): submit(frame, camera=name).")
    height: int | None = Field(
        None,
        ge=1,
        le=65536,
        description="Its frames' height, the size frame_slot(camera=...) lends (frames of any size are accepted).",
    )
    width: int | None = Field(None, ge=1, le=65536, description="Its frames' width (see height).")
    priority: Priority = Field(0, description=_GIVE_WAY + " Ranks after the head's.")

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not NAME_RE.match(v):
            raise ValueError(f"camera name {v!r} must start with a letter and use letters, digits, '_' or '-' (<= 64)")
        return v


class HeadConfig(ModelConfig):
    """One task head reading the foundation model's features."""

    name: str = Field(..., description="Unique head name (letters, digits, _ and -), used in results and topics.")
    cameras: list[str] | None = Field(
        None, description="The cameras this head serves, by name; null: every camera. Its rate is per camera."
    )
    priority: Priority = Field(0, description=_GIVE_WAY + " Ranks before the camera's.")
    postprocess: dict[str, Any] = Field(default_factory=dict, description="Postprocessing options of the recipe.")
    accept_backbone_mismatch: bool = Field(
        False,
        description="Run this head although its weights were trained on another backbone, or on other feature "
        "blocks (foundation_model.options.layers), than the ones it reads here: a warning instead of an error. "
        "Its outputs are degraded.",
    )
    output: OutputConfig = Field(default_factory=OutputConfig)  # type: ignore[arg-type]

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not NAME_RE.match(v):
            raise ValueError(f"head name {v!r} must start with a letter and use letters, digits, '_' or '-' (<= 64)")
        return v


class RuntimeConfig(_Strict):
    """Supervision and timing."""

    spare_heads: int = Field(
        1,
        ge=0,
        le=16,
        description="Heads Engine.add_head may add while the engine runs, at once: each has its place in the "
        "control block and the features mailbox from start, one more features slot per camera (Note [Heads at run "
        "time]).",
    )
    ready_timeout_s: float = Field(
        300.0,
        gt=0,
        le=86400,
        description="How long a worker's load and warm-up may go without progress (each batch size compiled or "
        "graph captured is progress) before the start gives up, and a build may wait for another in its process "
        "that makes none.",
    )
    stop_timeout_s: float = Field(3.0, gt=0, le=600, description="Grace time at stop before workers are terminated.")
    max_restarts: int = Field(
        5,
        ge=0,
        description="Restarts of one crashed worker within a minute before it is marked failed for good: a worker "
        "that fails now and then is restarted every time, one in a crash loop is marked failed.",
    )
    batch_window_ms: float = Field(
        5.0,
        ge=0,
        le=100,
        description="With several cameras: how long a model waits, after the first camera's frame, for the others' "
        "to run them as one batch (only for cameras whose next frame is due by then); a frame later than that goes "
        "in the next batch (counted as late). On an H200's host a 1080p frame takes about 1.5 ms to hand in: eight "
        "synchronised cameras submitting from threads of their own arrive within about 5 ms, from one thread within "
        "about 12 ms (docs/benchmarks.md). Keep it well under the cameras' frame period (the engine warns).",
    )
    hang_timeout_s: float | None = Field(
        60.0,
        gt=0,
        le=86400,
        description="A running worker silent this long is hung. Process mode: it is killed and restarted. Thread "
        "mode: it is reported (state 'hung', counted as a crash) and no longer waited for, and restarted once its "
        "thread returns (a Python thread cannot be killed); null: never.",
    )


class LoggingConfig(_Strict):
    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        "INFO",
        description="The least severe log messages written to logging.file: DEBUG, INFO, WARNING or ERROR (the "
        "terminal shows what the program's own logging does: the CLI's -v; worker processes' lines likewise).",
    )
    file: str | None = Field(None, description="Also log to this file.")


class WeightsConfig(_Strict):
    """Where checkpoints come from. Nothing is downloaded unless the catalog names it and offline is false."""

    offline: bool = Field(False, description="Never download; a missing checkpoint is an error naming its path.")
    random_weights: bool = Field(
        False, description="Use random weights instead of checkpoints (tests, benchmarks). Loudly logged."
    )


class EngineConfig(_Strict):
    """The whole engine: one foundation model, any number of heads."""

    name: str = Field("vpengine", description="Instance name (logs, topics).")
    mode: Literal["process", "thread"] = Field(
        "process",
        description="process: every model in its own process (fault isolation, MPS); thread: one process.",
    )
    device: str = Field("cpu", description="cpu, cuda or cuda:N.")
    precision: Precision = Field("fp32", description="Default precision of every model.")
    mps: Literal["auto", "required", "off"] = Field(
        "auto",
        description="CUDA MPS: use when a daemon is reachable (auto), insist (required), or not (off).",
    )
    input: InputConfig = Field(default_factory=InputConfig)  # type: ignore[arg-type]
    cameras: list[CameraConfig] = Field(
        default_factory=list,
        max_length=MAX_CAMERAS,
        description="Several cameras on one engine (when the GPU cannot keep up, the least important lane waits "
        "first: by its head's priority, then its camera's, then the camera last here); empty: one camera. Every "
        "camera's frames fit input.height x width.",
    )
    foundation_model: FoundationModelConfig = Field(default_factory=FoundationModelConfig)  # type: ignore[arg-type]
    heads: list[HeadConfig] = Field(default_factory=list)
    runtime: RuntimeConfig = Field(default_factory=RuntimeConfig)  # type: ignore[arg-type]
    logging: LoggingConfig = Field(default_factory=LoggingConfig)  # type: ignore[arg-type]
    weights: WeightsConfig = Field(default_factory=WeightsConfig)  # type: ignore[arg-type]

    @field_validator("mps", mode="before")
    @classmethod
    def _mps_off(cls, v: Any) -> Any:
        return "off" if v is False else v  # YAML 1.1 reads a bare `off` (mps: off, --set mps=off) as false

    @field_validator("device")
    @classmethod
    def _device(cls, v: str) -> str:
        if not _DEVICE_RE.match(v):
            raise ValueError(f"device {v!r} is not one of: cpu, cuda, cuda:N")
        return v

    @model_validator(mode="after")
    def _unique_heads(self) -> EngineConfig:
        names = [h.name for h in self.heads]
        dup = sorted({n for n in names if names.count(n) > 1})
        # each message starts with where it is, as a field's does (the formatter prints these without a location)
        if dup:
            raise ValueError(f"heads: head names must be unique; repeated: {dup}")
        if "foundation" in names:
            raise ValueError("heads: 'foundation' is reserved for the foundation model; rename that head")
        cams = [c.name for c in self.cameras]
        dup = sorted({n for n in cams if cams.count(n) > 1})
        if dup:
            raise ValueError(f"cameras: camera names must be unique; repeated: {dup}")
        for h in self.heads:
            unknown = [c for c in h.cameras or [] if c not in self.camera_names()]
            if unknown or h.cameras == []:
                none = "" if self.cameras else f" (the config has no cameras: its one camera is {DEFAULT_CAMERA!r})"
                raise ValueError(
                    f"heads.{h.name}.cameras: {h.cameras} must be some of the cameras {self.camera_names()}{none}"
                )
        return self

    def camera_names(self) -> list[str]:
        """The cameras, in the configured order: the configured ones, or the one camera ``camera``."""
        return [c.name for c in self.cameras] or [DEFAULT_CAMERA]

    def model_cameras(self, model: str) -> list[str]:
        """The cameras ``model`` (``foundation`` or a head) serves, in the configured order."""
        wanted = None if model == "foundation" else self.head(model).cameras
        return [c for c in self.camera_names() if wanted is None or c in wanted]

    def head(self, name: str) -> HeadConfig:
        for h in self.heads:
            if h.name == name:
                return h
        raise KeyError(f"no head named {name!r}; heads: {[h.name for h in self.heads]}")

    def model_names(self) -> list[str]:
        return ["foundation", *(h.name for h in self.heads)]

    def model(self, name: str) -> ModelConfig:
        """The foundation model's config (``foundation``) or a head's."""
        return self.foundation_model if name == "foundation" else self.head(name)

    @staticmethod
    def model_path(name: str) -> str:
        """Where model ``name`` stands in a config, as errors and ``--set`` name it: ``foundation_model`` or
        ``heads.NAME``."""
        return "foundation_model" if name == "foundation" else f"heads.{name}"

    def process_mates(self, name: str) -> list[str]:
        """The models that share model ``name``'s worker process, ``name`` included, foundation first and the heads
        in order (Note [Process groups] in runtime/process.py); ``[name]`` alone in thread mode or when it names no
        process."""
        group = self.model(name).process
        if group is None or self.mode != "process":
            return [name]
        return [n for n in self.model_names() if self.model(n).process == group]


# ------------------------------------------------------------------------------------------------- loading
#: Bounds on a config, checked before anything expands it. A 1 KB YAML file of nested aliases (or merge keys) can
#: stand for billions of values; validation, error messages and the copy each worker gets would expand them all.
MAX_VALUES = 100_000
MAX_DEPTH = 64
_SHOWN_CHARS = 200  # at most this much of any value (or error text) is quoted in an error


def _clip(text: str, limit: int = _SHOWN_CHARS) -> str:
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def _named_loc(loc: tuple[Any, ...], data: Any) -> str:
    """An error's place as a user writes it: a list item by its ``name`` where it has one (``heads.depth.rate_hz``,
    as ``--set`` takes it), else by its index."""
    parts: list[str] = []
    node = data
    for p in loc:
        if isinstance(p, int) and isinstance(node, list) and 0 <= p < len(node):
            names = [x.get("name") if isinstance(x, dict) else None for x in node]
            node = node[p]
            name = names[p]
            # only a valid name that no other item has: --set would take anything else as another item, or none
            usable = isinstance(name, str) and NAME_RE.match(name) is not None and names.count(name) == 1
            parts.append(str(name) if usable else str(p))
        else:
            node = node.get(p) if isinstance(node, dict) else None
            parts.append(str(p))
    return ".".join(parts)


def _format_validation_error(err: ValidationError, source: str, data: Any = None) -> str:
    lines = [f"invalid configuration{f' in {source}' if source else ''}:"]
    for e in err.errors():
        loc = _clip(_named_loc(e["loc"], data) or "(top level)")
        if e["type"] == "extra_forbidden":
            parent = _model_at(EngineConfig, e["loc"][:-1])
            accepted = sorted(parent.model_fields) if parent else []
            near = difflib.get_close_matches(str(e["loc"][-1]), accepted, n=1, cutoff=0.75)
            guess = f"did you mean {near[0]!r}? " if near else ""
            lines.append(f"  {loc}: unknown key ({guess}accepted here: {', '.join(accepted)})")
        else:
            given = e.get("input")
            shown = _clip(json.dumps(given, default=str)) if not isinstance(given, dict) else "{...}"
            msg = _clip(e["msg"], 4 * _SHOWN_CHARS)
            if e["type"] == "value_error" and not e["loc"]:  # a check across fields: its message says where
                lines.append(f"  {msg.removeprefix('Value error, ')}")
                continue
            # a validator of ours quoting the value already; a mapping's "{...}" says nothing
            said = (e["type"] == "value_error" and ", got " in msg) or isinstance(given, dict)
            lines.append(f"  {loc}: {msg}" if said else f"  {loc}: {msg} (got {shown})")
    return "\n".join(lines)


def _check_size(root: Any, children: Any, where: str) -> None:
    """Refuse a config that nests deeper than ``MAX_DEPTH`` or expands to more than ``MAX_VALUES`` values, without
    expanding it: a container that appears many times (a YAML alias) is measured once, and one that contains
    itself is refused. ``children(x)``: x's items, or None for a scalar (works on YAML nodes and on Python data)."""
    where = f" in {where}" if where else ""
    sizes: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[Any, int, bool]] = [(root, 1, False)]
    while stack:
        obj, depth, done = stack.pop()
        items = children(obj)
        if items is None:
            continue
        key = id(obj)
        if done:
            on_path.discard(key)
            n = 1 + sum(sizes.get(id(c), 1) if children(c) is not None else 1 for c in items)
            if n > MAX_VALUES:
                raise ConfigError(
                    f"configuration{where} expands to more than {MAX_VALUES} values (YAML aliases that "
                    "refer to aliases multiply); refused"
                )
            sizes[key] = n
            continue
        if key in sizes:
            continue
        if key in on_path:
            raise ConfigError(f"configuration{where} contains itself (a YAML alias inside its own anchor)")
        if depth > MAX_DEPTH:
            raise ConfigError(f"configuration{where} nests deeper than {MAX_DEPTH} levels")
        on_path.add(key)
        stack.append((obj, depth, True))
        stack.extend((c, depth + 1, False) for c in items)


def _data_items(x: Any) -> Any:
    if isinstance(x, dict):
        return list(x.values())
    return list(x) if isinstance(x, (list, tuple)) else None


def _node_items(node: Any) -> Any:
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    return list(node.value) if isinstance(node, yaml.SequenceNode) else None


def load_yaml(text: str, where: str, subject: str | None = None) -> Any:
    """``yaml.safe_load``, refusing documents that would expand past the bounds (checked on the parsed nodes,
    where aliases are still shared, before any Python object is built) and mappings that give a key twice.
    ``where`` names the text in a bounds error, ``subject`` (default: the config file ``where``) in a key's."""
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_size(node, _node_items, where)
        _check_unique_keys(node, subject or f"config file {where}")
        return loader.construct_document(node)
    finally:
        loader.dispose()


def _check_unique_keys(root: Any, subject: str) -> None:
    """Refuse a mapping that names a key twice: YAML keeps the last silently, so a second ``heads:`` block pasted
    below the first would drop every head above it. Named with both lines."""
    seen: set[int] = set()
    stack = [root]
    while stack:
        node = stack.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        if isinstance(node, yaml.MappingNode):
            first: dict[Any, int] = {}
            for key, _ in node.value:
                if isinstance(key, yaml.ScalarNode) and key.value != "<<":
                    line = key.start_mark.line + 1
                    if key.value in first:
                        lines = "" if first[key.value] == line == 1 else f" (lines {first[key.value]} and {line})"
                        raise ConfigError(
                            f"{subject}: key {key.value!r} is given twice in one mapping{lines}; YAML would keep "
                            "only the last: merge them"
                        )
                    first[key.value] = line
        stack.extend(_node_items(node) or [])


def _unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``json.loads``' object hook: a JSON object that names a key twice is refused, as in YAML."""
    keys = [k for k, _ in pairs]
    twice = sorted({k for k in keys if keys.count(k) > 1})
    if twice:
        raise ConfigError(f"key {twice[0]!r} is given twice in one JSON object; only the last would count: merge them")
    return dict(pairs)


def _model_at(model: type[BaseModel], loc: tuple[Any, ...]) -> type[BaseModel] | None:
    for part in loc:
        if isinstance(part, int):
            continue
        field = model.model_fields.get(str(part))
        if field is None:
            return None
        ann = field.annotation
        args = getattr(ann, "__args__", None)
        candidates = [ann, *(args or [])]
        nxt = next((c for c in candidates if isinstance(c, type) and issubclass(c, BaseModel)), None)
        if nxt is None:
            return None
        model = nxt
    return model


def parse_value(text: str, subject: str = "a command-line override") -> Any:
    """A command-line value: YAML scalars and lists (``5``, ``null``, ``true``, ``[1, 2]``), else the string.
    ``subject`` names it in an error (a key given twice in a mapping)."""
    try:
        return load_yaml(text, "a command-line override", subject)
    except yaml.YAMLError:
        return text
    except RecursionError:
        raise ConfigError(f"override value {_clip(text)!r} nests too deeply") from None


def apply_override(data: dict[str, Any], dotted: str) -> None:
    """Apply ``a.b.c=value`` to a raw config dict. Heads may be addressed by name or index."""
    if "=" not in dotted:
        raise ConfigError(f"override {dotted!r} must look like key.path=value")
    path, _, raw = dotted.partition("=")
    parts = [p for p in path.strip().split(".") if p]
    if not parts:
        raise ConfigError(f"override {dotted!r} has an empty key path")
    node: Any = data
    for i, part in enumerate(parts[:-1]):
        if isinstance(node, list):
            node = node[_list_index(node, part, ".".join(parts[: i + 1]))]
        else:  # the lists of named entries are lists even when the config has none yet (cameras.rear.priority)
            node = node.setdefault(part, [] if node is data and part in _NAMED_LISTS else {})
        if not isinstance(node, (dict, list)):
            raise ConfigError(f"override {dotted!r}: {'.'.join(parts[: i + 1])} is a value, not a section")
    last = parts[-1]
    if isinstance(node, list):
        node[_list_index(node, last, path)] = parse_value(raw, f"override {dotted!r}")
    else:
        node[last] = parse_value(raw, f"override {dotted!r}")


#: The config's top-level lists whose entries --set names (heads.depth.rate_hz, cameras.rear.priority)
_NAMED_LISTS = ("heads", "cameras")


def _list_index(items: list[Any], key: str, where: str) -> int:
    if key.isdigit():
        idx = int(key)
        if idx >= len(items):
            raise ConfigError(f"override path {where}: index {idx} out of range (there are {len(items)})")
        return idx
    for i, item in enumerate(items):
        if isinstance(item, dict) and item.get("name") == key:
            return i
    names = [item.get("name") for item in items if isinstance(item, dict)]
    if not names:
        section = where.split(".")[0]
        raise ConfigError(
            f"override path {where}: the config has no {section} (so none named {key!r}); add it first, e.g. "
            f"--set '{section}=[{{name: {key}}}]'"
        )
    raise ConfigError(f"override path {where}: no entry named {key!r}; names: {names}")


def load_raw(path: str | Path) -> dict[str, Any]:
    """A config file's mapping: ``path`` is a file, or the name of a config shipped with the package (``tiny``)."""
    from vpengine import configs

    try:
        path = configs.resolve(path)
    except FileNotFoundError as e:
        raise ConfigError(str(e)) from None
    kind = "JSON" if path.suffix == ".json" else "YAML"
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(
            f"config file {str(path)!r} is not UTF-8 text ({e.reason} at byte {e.start}); expected {kind}"
        ) from None
    try:
        data = json.loads(text, object_pairs_hook=_unique_pairs) if kind == "JSON" else load_yaml(text, repr(str(path)))
    except (json.JSONDecodeError, yaml.YAMLError) as e:
        raise ConfigError(f"config file {str(path)!r} is not valid {kind}: {_syntax_error(e, text)}") from None
    except RecursionError:
        raise ConfigError(f"config file {str(path)!r} nests too deeply to parse") from None
    except ConfigError as e:
        if kind == "JSON":  # a key given twice: its object hook knows no file (nor lines)
            raise ConfigError(f"config file {str(path)!r}: {e}") from None
        raise
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {str(path)!r} must hold a mapping at the top level, got {type(data).__name__}")
    return data


def _syntax_error(e: json.JSONDecodeError | yaml.YAMLError, text: str) -> str:
    """A parser's complaint in one line: where (line and column, from 1) and why, without the parser's own
    multi-line layout (which names ``<unicode string>`` rather than the file)."""
    if isinstance(e, json.JSONDecodeError):
        return f"line {e.lineno}, column {e.colno}: {e.msg}"
    if isinstance(e, yaml.reader.ReaderError):  # a character YAML does not allow; it has an offset, not a mark
        before = text[: e.position]
        line, column = before.count("\n") + 1, e.position - (before.rfind("\n") + 1) + 1
        ch = e.character
        shown = f"U+{ch:04X}" if isinstance(ch, int) else repr(ch)  # an int for a code point, bytes when undecodable
        return f"line {line}, column {column}: character {shown} is not allowed in YAML ({e.reason})"
    mark = getattr(e, "problem_mark", None)
    problem = getattr(e, "problem", None)
    if mark is None or problem is None:
        return _clip(" ".join(str(e).split()), 300)
    context = getattr(e, "context", None)
    why = f"{problem} ({context})" if context else problem
    return f"line {mark.line + 1}, column {mark.column + 1}: {_clip(' '.join(why.split()), 300)}"


def load_config(
    source: str | Path | dict[str, Any] | EngineConfig | None = None, overrides: list[str] | None = None
) -> EngineConfig:
    """Load and validate a config from a YAML/JSON file, a dict or an EngineConfig, then apply dotted overrides
    (a list of ``key.path=value``, or one such str)."""
    if isinstance(overrides, str):  # one override, not its characters
        overrides = [overrides]
    if isinstance(source, EngineConfig):
        if not overrides:
            return source
        data = source.model_dump()
        where = ""
    elif isinstance(source, dict):
        _check_size(source, _data_items, "")
        data, where = json.loads(json.dumps(source)), ""
    elif source is None:
        data, where = {}, ""
    else:
        data, where = load_raw(source), str(source)
    for o in overrides or []:
        apply_override(data, o)
    _check_size(data, _data_items, repr(where) if where else "")
    try:
        return EngineConfig.model_validate(data)
    except ValidationError as e:
        raise ConfigError(_format_validation_error(e, where, data)) from None


def dump_config(cfg: EngineConfig) -> str:
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)
