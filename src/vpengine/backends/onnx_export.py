"""Export any traceable :class:`Model` to ONNX, and the on-disk cache of exports.

The exported graph has the model's own names: one graph input per ``input_spec`` key and one graph output per
``output_spec`` key, with the declared dtypes and static shapes for a batch of one frame, ``[1, *shape]`` (checked
after every export; Note [Batched models] in models/base.py: the ONNX backend runs a batch as one run per frame). Exports always run on
the CPU, from a host copy of the model cast to the requested precision and run under autocast exactly as the eager
backend runs it (Note [Precision]): the file depends on the weights and the specs, never on the device the engine
runs on, and the model in the caller's hands is left untouched.

Note [ONNX cache key]
~~~~~~~~~~~~~~~~~~~~~
An export is reused only when everything that shaped the graph is the same. The key hashes:

* the model class and, for every submodule, its class and its plain attributes (numbers, strings, tuples, pydantic
  options): thresholds, flags and sizes are baked into the graph as constants, but appear in no state dict;
* every parameter and buffer, persistent or not (normalisation means, anchor grids), by content;
* the input and output specs (a new input size is a new graph), the precision, the opset and the exporter;
* the source files of the model's classes and of this module, and the torch/onnx/onnxscript versions: an edited
  forward or a new exporter may produce a different graph from the same weights.

A cache entry is a folder ``<cache>/onnx/<Model>-<precision>-<key[:16]>/`` with ``model.onnx`` (plus external
weight files for models over 2 GB) and ``manifest.json`` (the full key, the key's inputs, the specs). It is written
into a temporary folder and renamed into place, so a crash or a concurrent export never leaves a half-written entry
that looks valid. Entries are never deleted automatically; removing the folder is always safe.
"""

from __future__ import annotations

import contextlib
import copy
import enum
import hashlib
import importlib.metadata
import inspect
import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from pydantic import BaseModel
from torch import nn

from vpengine.backends.base import PrecisionRunner, cast_model_, precision_dtype
from vpengine.backends.options import BackendError, OnnxOptions
from vpengine.models.base import Model, Pipeline, random_inputs
from vpengine.specs import SpecDict, TensorSpec

log = logging.getLogger("vpengine.backends")

#: Bump when the export recipe changes in a way the key cannot see.
EXPORT_FORMAT = 1
#: Above this many bytes of weights, initialisers go to external data files (protobuf caps a file at 2 GB).
EXTERNAL_DATA_BYTES = 1_500_000_000
ONNX_PRECISIONS = ("fp32", "fp16")


def check_onnx_precision(precision: str, name: str) -> None:
    """ONNX exports exist for fp32 and fp16 only; bf16 fails with the reason."""
    precision_dtype(precision, name)
    if precision not in ONNX_PRECISIONS:
        raise BackendError(
            f"{name}: precision {precision!r} is not available with ONNX: the ONNX operators TensorRT and ONNX "
            "Runtime read have no bfloat16 versions for Conv, TopK and others, and ONNX Runtime's CPU provider "
            f"has almost no bfloat16 kernels. Accepted here: {', '.join(ONNX_PRECISIONS)}; run bf16 with "
            "backend 'compile' or 'eager'"
        )


class _FlatIO(nn.Module):
    """Positional inputs in ``input_spec`` order -> tuple of outputs in ``output_spec`` order, at a precision.

    Exporters name graph inputs and outputs by position; flattening the dict here makes those positions ours.
    """

    def __init__(self, model: Model, dtype: torch.dtype) -> None:
        super().__init__()
        self.model = model
        self.in_keys = list(model.input_spec)
        self.out_keys = list(model.output_spec)
        self.runner = PrecisionRunner(model, model.output_spec, dtype, "cpu")

    def forward(self, *xs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = self.runner(dict(zip(self.in_keys, xs)))
        missing = [k for k in self.out_keys if k not in out]
        if missing:
            raise BackendError(f"the model's forward does not return declared outputs {missing}")
        return tuple(out[k] for k in self.out_keys)


def cpu_copy(model: Model) -> Model:
    """A deep copy of ``model`` with every parameter and buffer on the CPU.

    Tensors are copied to the host one at a time through deepcopy's memo, so a model on a GPU is never duplicated on
    the GPU.
    """
    memo: dict[int, Any] = {}
    for t in [*model.parameters(), *model.buffers()]:
        if id(t) in memo:
            continue
        host = t.detach().to("cpu", copy=True)
        memo[id(t)] = nn.Parameter(host, requires_grad=False) if isinstance(t, nn.Parameter) else host
    return copy.deepcopy(model, memo)


def _weight_bytes(model: nn.Module) -> int:
    return sum(t.numel() * t.element_size() for t in [*model.parameters(), *model.buffers()])


def _short(exc: BaseException, limit: int = 800) -> str:
    text = f"{type(exc).__name__}: {exc}".strip()
    return text if len(text) <= limit else text[:limit] + " ..."


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """The dynamo exporter's optimiser logs every rewrite at INFO; keep a -v run of vpengine readable."""
    loggers = [logging.getLogger(n) for n in ("onnxscript", "onnx_ir")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def export_onnx(*args: Any, **kwargs: Any) -> dict[str, Any]:
    """Export and verify under exact preprocessing (see ``_export_onnx``)."""
    from vpengine.models.preprocess import exact_preprocessing

    with exact_preprocessing():
        return _export_onnx(*args, **kwargs)


def _export_onnx(
    model: Model,
    path: str | Path,
    precision: str = "fp32",
    opset: int = 18,
    exporter: str = "dynamo",
    name: str | None = None,
    verify: bool = True,
) -> dict[str, Any]:
    """Export ``model`` to ``path`` (inputs/outputs named after its specs), check it, and verify it.

    Verification runs the file on ONNX Runtime's CPU provider and the model in PyTorch on two inputs -- the one the
    exporter traced and a fresh one -- and refuses the export if they disagree: a graph that froze a data-dependent
    value (a Python int taken from a tensor) passes every structural check but is wrong on the next frame.
    Returns ``{"export_s": seconds, "verification": report or None}``. Raises BackendError with the exporter's
    message when the model cannot be exported, the graph does not match the declared specs, or verification fails.
    """
    name = name or type(model).__name__
    check_onnx_precision(precision, name)
    dtype = precision_dtype(precision, name)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    try:
        host = cast_model_(cpu_copy(model).eval(), dtype)
    except Exception as e:
        raise BackendError(f"{name}: cannot copy the model to the CPU for export: {_short(e)}") from e
    flat = _FlatIO(host, dtype).eval()
    example = model.example_inputs("cpu")
    args = tuple(example[k] for k in flat.in_keys)
    external = _weight_bytes(host) > EXTERNAL_DATA_BYTES
    try:
        with torch.no_grad(), _quiet_exporter():
            if exporter == "dynamo":
                program = torch.onnx.export(
                    flat,
                    args,
                    None,
                    input_names=flat.in_keys,
                    output_names=flat.out_keys,
                    opset_version=opset,
                    dynamo=True,
                    verbose=False,
                )
                assert program is not None
                program.save(str(path), external_data=external)
            elif exporter == "torchscript":
                torch.onnx.export(
                    flat,
                    args,
                    str(path),
                    input_names=flat.in_keys,
                    output_names=flat.out_keys,
                    opset_version=opset,
                    dynamo=False,
                    do_constant_folding=True,
                )
            else:
                raise BackendError(f"{name}: unknown exporter {exporter!r}; accepted: 'dynamo', 'torchscript'")
    except BackendError:
        raise
    except ModuleNotFoundError as e:
        if (e.name or "").partition(".")[0] not in ("onnx", "onnxscript", "onnxruntime"):
            raise BackendError(f"{name}: ONNX export ({exporter}, opset {opset}) failed: {_short(e)}") from e
        raise BackendError(  # the exporters import onnx and onnxscript only now
            f"{name}: ONNX export ({exporter}) needs {e.name or 'a module that is missing'}, which is not installed: "
            "pip install 'vpengine[onnx]'"
        ) from e
    except Exception as e:
        raise BackendError(f"{name}: ONNX export ({exporter}, opset {opset}) failed: {_short(e)}") from e
    check_onnx(
        path,
        model.input_spec,
        model.output_spec,
        name,
        allow_unused_inputs=exporter == "torchscript",
        opset=opset,
    )
    report = None
    if verify:
        runner = PrecisionRunner(host, model.output_spec, dtype, "cpu")
        # a batch of one frame, as the graph holds
        report = verify_export(runner, [example, random_inputs(model.input_spec, 1)], path, precision)
        if not report["ok"]:
            bad = "; ".join(f"{k}: {describe_check(r)}" for k, r in report["outputs"].items() if not r["ok"])
            raise BackendError(
                f"{name}: the ONNX export ({exporter}) does not reproduce PyTorch: {bad}. The graph froze something "
                f"the model computes from its inputs (a Python int or branch taken from a tensor, a data-dependent "
                f"shape); the file is at {path}"
            )
    return {"export_s": time.perf_counter() - t0, "verification": report}


# ------------------------------------------------------------------------------------------------ verification
#: Largest tolerated error of a float output, relative to that output's largest magnitude, per precision.
VERIFY_TOLERANCE = {"fp32": 1e-3, "fp16": 2e-2}
#: Largest tolerated fraction of differing elements of an integer output (argmax ties may break differently);
#: for a scalar such as a detection count, any difference fails.
VERIFY_INT_MISMATCH = 0.01


def describe_check(r: dict[str, Any]) -> str:
    """One output's verification result in words."""
    if "relative_error" in r:
        return f"error {r['relative_error']:.1e} of the output's scale (limit {r['limit']:g})"
    return f"{r['mismatch_fraction']:.2%} of elements differ (limit {r['limit']:.0%})"


def verify_export(
    run: Any, inputs_list: list[dict[str, torch.Tensor]], path: str | Path, precision: str
) -> dict[str, Any]:
    """Run ``path`` on ONNX Runtime (CPU) and ``run`` (the PyTorch model) on each of ``inputs_list``; the worst
    error per output over all inputs, and whether every one is within the limits."""
    import numpy as np
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = torch.get_num_threads()
    so.log_severity_level = 3
    session = ort.InferenceSession(str(path), sess_options=so, providers=["CPUExecutionProvider"])
    names_in = [i.name for i in session.get_inputs()]
    names_out = [o.name for o in session.get_outputs()]
    limit = VERIFY_TOLERANCE[precision]
    outputs: dict[str, dict[str, Any]] = {}
    for inputs in inputs_list:
        with torch.inference_mode():
            want = {k: v.cpu().numpy() for k, v in run(inputs).items()}
        got = dict(zip(names_out, session.run(None, {k: inputs[k].numpy() for k in names_in})))
        for k, ref in want.items():
            g = np.asarray(got[k])
            if ref.dtype.kind == "f":
                r64, g64 = ref.astype(np.float64), g.astype(np.float64)
                scale = max(float(np.abs(r64).max(initial=0.0)), 1e-12)
                err = float(np.abs(g64 - r64).max(initial=0.0)) / scale if np.isfinite(g64).all() else np.inf
                worst = max(err, outputs.get(k, {}).get("relative_error", 0.0))
                outputs[k] = {"relative_error": worst, "limit": limit, "ok": worst <= limit}
            else:
                frac = float((g != ref).mean()) if ref.size else 0.0
                ok = frac <= VERIFY_INT_MISMATCH
                prev = outputs.get(k, {"mismatch_fraction": 0.0, "ok": True})
                outputs[k] = {
                    "mismatch_fraction": max(frac, prev["mismatch_fraction"]),
                    "limit": VERIFY_INT_MISMATCH,
                    "ok": ok and prev["ok"],
                }
    return {
        "runtime": "onnxruntime CPUExecutionProvider",
        "inputs": len(inputs_list),
        "outputs": outputs,
        "ok": all(r["ok"] for r in outputs.values()),
    }


def _onnx_dtype_name(elem_type: int) -> str:
    import onnx

    try:
        return str(onnx.helper.tensor_dtype_to_np_dtype(elem_type))
    except Exception:
        return onnx.TensorProto.DataType.Name(elem_type).lower()


def _value_info(vi: Any) -> tuple[str, tuple[int | str, ...]]:
    tt = vi.type.tensor_type
    dims = tuple(d.dim_value if d.HasField("dim_value") else (d.dim_param or "?") for d in tt.shape.dim)
    return _onnx_dtype_name(tt.elem_type), dims


def check_onnx(
    path: str | Path,
    input_spec: SpecDict,
    output_spec: SpecDict,
    name: str,
    allow_unused_inputs: bool = False,
    opset: int | None = None,
) -> None:
    """``onnx.checker`` on the file, its opset (if given), then its graph inputs/outputs against the specs (names,
    dtypes, and the spec's shapes for a batch of one: ``[1, *shape]``)."""
    import onnx

    try:
        onnx.checker.check_model(str(path), full_check=True)
    except Exception as e:
        raise BackendError(f"{name}: exported ONNX graph {str(path)!r} fails onnx.checker: {_short(e)}") from e
    proto = onnx.load(str(path), load_external_data=False)
    written = next((o.version for o in proto.opset_import if o.domain in ("", "ai.onnx")), None)
    if opset is not None and written != opset:
        # The dynamo exporter converts down from its native opset and keeps the newer one when it cannot.
        raise BackendError(
            f"{name}: asked for ONNX opset {opset} but the exporter could only write opset {written} (an operator "
            f"has no equivalent in opset {opset}, e.g. antialiased Resize needs 18); use opset {written} or later"
        )
    graph = proto.graph
    initializers = {i.name for i in graph.initializer}
    got_in = {vi.name: _value_info(vi) for vi in graph.input if vi.name not in initializers}
    got_out = {vi.name: _value_info(vi) for vi in graph.output}
    problems = []

    def compare(kind: str, got: dict[str, tuple[str, tuple[int | str, ...]]], want: dict[str, TensorSpec]) -> None:
        for k, spec in want.items():
            if k not in got:
                if not (kind == "input" and allow_unused_inputs):
                    problems.append(f"{kind} {k!r} is missing")
                continue
            dt, shape = got[k]
            if dt != spec.dtype or shape != (1, *spec.shape):
                problems.append(
                    f"{kind} {k!r} is {dt}{list(shape)}, declared {spec} per frame, so "
                    f"{spec.dtype}{[1, *spec.shape]} for the batch of one the graph holds"
                )
        problems.extend(f"unexpected {kind} {k!r}" for k in got if k not in want)

    compare("input", got_in, input_spec)
    compare("output", got_out, output_spec)
    if problems:
        raise BackendError(f"{name}: exported ONNX graph does not match the model's specs: {'; '.join(problems)}")


# ------------------------------------------------------------------------------------------------ cache key
def _plain(v: Any, depth: int = 0) -> Any:
    """A JSON-able description of an attribute value, for the cache key (Note [ONNX cache key])."""
    if v is None or isinstance(v, (bool, int, str)):
        return v
    if isinstance(v, float):
        return repr(v)  # exact, and nan/inf survive JSON
    if isinstance(v, enum.Enum):
        return _plain(v.value, depth)
    if isinstance(v, (torch.dtype, torch.device)):
        return str(v)
    if isinstance(v, torch.Tensor):
        return {"tensor": _tensor_hash(v)}
    if depth > 4:
        return type(v).__qualname__
    if isinstance(v, BaseModel):
        return _plain(v.model_dump(mode="json"), depth + 1)
    if isinstance(v, (list, tuple)):
        return [_plain(x, depth + 1) for x in v]
    if isinstance(v, (set, frozenset)):
        return sorted(json.dumps(_plain(x, depth + 1), sort_keys=True) for x in v)
    if isinstance(v, dict):
        return {str(k): _plain(x, depth + 1) for k, x in v.items()}
    if isinstance(v, nn.Module):
        return f"{type(v).__module__}.{type(v).__qualname__}"
    if callable(v):
        return f"{getattr(v, '__module__', '')}.{getattr(v, '__qualname__', type(v).__qualname__)}"
    if hasattr(v, "__dict__"):
        return {"type": type(v).__qualname__, "attrs": _plain(vars(v), depth + 1)}
    return type(v).__qualname__


def _tensor_hash(t: torch.Tensor) -> str:
    h = hashlib.blake2b(digest_size=16)
    h.update(f"{t.dtype}{tuple(t.shape)}".encode())
    h.update(t.detach().to("cpu").contiguous().reshape(-1).view(torch.uint8).numpy().data)
    return h.hexdigest()


def _tensors_digest(model: nn.Module) -> str:
    h = hashlib.blake2b(digest_size=32)
    for prefix, tensors in (("p", model.named_parameters()), ("b", model.named_buffers())):
        for n, t in tensors:
            h.update(f"{prefix}:{n}:{_tensor_hash(t)};".encode())
    return h.hexdigest()


def _modules_fingerprint(model: nn.Module) -> list[Any]:
    out = []
    for n, m in model.named_modules():
        attrs = {k: _plain(v) for k, v in sorted(vars(m).items()) if not k.startswith("_") and k != "training"}
        out.append([n, f"{type(m).__module__}.{type(m).__qualname__}", attrs])
    return out


def _sources_digest(model: nn.Module) -> dict[str, str]:
    files: dict[str, str] = {}
    classes = {type(m) for m in model.modules()}
    for cls in classes:
        for c in cls.__mro__:
            mod = c.__module__ or ""
            if mod.startswith(("torch", "builtins")) or mod in files:
                continue
            try:
                src = inspect.getsourcefile(c)
            except TypeError:
                src = None
            if src and os.path.isfile(src):
                files[mod] = hashlib.sha256(Path(src).read_bytes()).hexdigest()
    files[__name__] = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()
    return dict(sorted(files.items()))


def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "none"


def resolve_exporter(exporter: str, model: Model) -> str:
    """``auto`` -> the exporter the model's parts ask for (``Model.onnx_exporter``): torchscript if any part needs it."""
    if exporter != "auto":
        return exporter
    wanted = {m.onnx_exporter for m in model.modules() if isinstance(m, Model)}
    return "torchscript" if "torchscript" in wanted else "dynamo"


def cache_key(model: Model, precision: str, opset: int, exporter: str) -> tuple[str, dict[str, Any]]:
    """The cache key of an export and what it was computed from (Note [ONNX cache key])."""
    material = {
        "format": EXPORT_FORMAT,
        "class": f"{type(model).__module__}.{type(model).__qualname__}",
        "modules": _modules_fingerprint(model),
        "tensors": _tensors_digest(model),
        "inputs": {k: s.to_json() for k, s in model.input_spec.items()},
        "outputs": {k: s.to_json() for k, s in model.output_spec.items()},
        "precision": precision,
        "export": {"opset": opset, "exporter": exporter},
        "sources": _sources_digest(model),
        "versions": {
            "torch": torch.__version__,
            "onnx": _version("onnx"),
            "onnxscript": _version("onnxscript"),
        },
    }
    key = hashlib.sha256(json.dumps(material, sort_keys=True).encode()).hexdigest()
    return key, material


def model_label(model: Model) -> str:
    """``TinyViT`` or ``ImagePreprocess+TinyViT`` (pipelines): the readable part of a cache folder name."""
    if isinstance(model, Pipeline):
        return "+".join(type(m).__name__ for m in model.stages)
    return type(model).__name__


# ------------------------------------------------------------------------------------------------ cache
@dataclass(frozen=True)
class OnnxArtifact:
    """An ONNX file ready to load."""

    path: Path
    key: str
    #: True if this call exported the model; False if it reused a cached export.
    exported: bool
    manifest: dict[str, Any]


class OnnxCache:
    """Exports by key under ``root`` (``<vpengine cache>/onnx``); see Note [ONNX cache key]."""

    MODEL_FILE = "model.onnx"
    MANIFEST = "manifest.json"

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    def _entry(self, model: Model, precision: str, key: str) -> Path:
        return self.root / f"{model_label(model)}-{precision}-{key[:16]}"

    def _load_manifest(self, entry: Path, key: str) -> dict[str, Any] | None:
        try:
            manifest = json.loads((entry / self.MANIFEST).read_text())
        except (OSError, ValueError):
            return None
        if manifest.get("key") != key or not (entry / self.MODEL_FILE).is_file():
            return None
        if not all((entry / f).is_file() for f in manifest.get("files", [])):
            return None
        return dict(manifest)

    def get_or_export(
        self, model: Model, precision: str, opts: OnnxOptions, name: str, force: bool = False
    ) -> OnnxArtifact:
        """The cached export of ``model`` if its key matches (and ``opts.cache`` and not ``force``), else a new one."""
        check_onnx_precision(precision, name)
        exporter = resolve_exporter(opts.exporter, model)
        key, material = cache_key(model, precision, opts.opset, exporter)
        entry = self._entry(model, precision, key)
        if opts.cache and not force:
            manifest = self._load_manifest(entry, key)
            if manifest is not None:
                log.info("%s: reusing ONNX export %s", name, entry)
                return OnnxArtifact(entry / self.MODEL_FILE, key, False, manifest)
        self.root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{entry.name}-", dir=self.root))
        try:
            result = export_onnx(
                model, tmp / self.MODEL_FILE, precision, opts.opset, exporter, name, verify=opts.verify
            )
            seconds = result["export_s"]
            manifest = {
                "key": key,
                "name": name,
                "precision": precision,
                "opset": opts.opset,
                "exporter": exporter,
                "inputs": material["inputs"],
                "outputs": material["outputs"],
                "export_s": round(seconds, 3),
                "verification": result["verification"],
                "created": time.time(),
                "files": sorted(p.name for p in tmp.iterdir()),
                "material": material,
            }
            (tmp / self.MANIFEST).write_text(json.dumps(manifest, indent=1))
            if entry.exists():  # stale (bad manifest), forced, or cache disabled: replace it
                shutil.rmtree(entry, ignore_errors=True)
            try:
                os.rename(tmp, entry)
            except OSError:
                # Another process renamed its identical export into place between our check and our rename.
                if self._load_manifest(entry, key) is None:
                    raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        log.info("%s: exported to ONNX in %.1f s: %s", name, seconds, entry)
        return OnnxArtifact(entry / self.MODEL_FILE, key, True, manifest)
