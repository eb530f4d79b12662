"""ONNX Runtime: run the model's ONNX export (cached, see ``onnx_export.py``) with IO binding.

The export holds one frame (every graph input and output has a leading batch dimension of 1: Faster R-CNN's traced
graph cannot have another, its RPN and RoI heads loop over the images in Python), so a batch of B frames is B runs,
one per frame (Note [Executor contract] in base.py). Outputs are bound once, at construction, to preallocated
tensors for ``max_batch`` frames on the model's device -- one IO binding per frame of a batch, bound to that frame
of the outputs -- so ONNX Runtime writes straight into them and a run allocates no output memory; inputs are rebound
every call to the tensors the worker hands in (mailbox views whose addresses change per slot), which is just a
pointer swap. Inputs that are not contiguous or not on the model's device go through preallocated staging tensors.

On CUDA, ONNX Runtime runs on the worker's own stream (the CUDA provider's ``user_compute_stream``), so the copies
the worker queues before and after a run are ordered with it by the stream itself. fp16 models on the CPU provider
run, but ONNX Runtime computes every operator that has no fp16 CPU kernel in fp32 between inserted Cast nodes: the
results are fp16-rounded and there is no speed-up; fp16 pays off on the CUDA and TensorRT providers.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import torch

from vpengine.backends.base import Executor, tensor_bytes
from vpengine.backends.onnx_export import OnnxArtifact, OnnxCache, check_onnx_precision
from vpengine.backends.options import BackendError, OnnxOptions
from vpengine.models.base import Model

log = logging.getLogger("vpengine.backends")

_NUMPY: dict[torch.dtype, type] = {
    torch.float32: np.float32,
    torch.float16: np.float16,
    torch.float64: np.float64,
    torch.uint8: np.uint8,
    torch.int8: np.int8,
    torch.int16: np.int16,
    torch.int32: np.int32,
    torch.int64: np.int64,
    torch.bool: np.bool_,
}
_GPU_PROVIDERS = ("CUDAExecutionProvider", "TensorrtExecutionProvider")
_OPT_LEVELS = {
    "disable": "ORT_DISABLE_ALL",
    "basic": "ORT_ENABLE_BASIC",
    "extended": "ORT_ENABLE_EXTENDED",
    "all": "ORT_ENABLE_ALL",
}


class _LoadError(BackendError):
    """ONNX Runtime refused the file (or the provider set-up)."""


def _import_ort(name: str) -> Any:
    try:
        import onnxruntime
    except ImportError:
        raise BackendError(
            f"{name}: backend 'onnx' needs onnxruntime (pip install 'vpengine[onnx]', or onnxruntime-gpu for CUDA)"
        ) from None
    return onnxruntime


class OnnxExecutor(Executor):
    """ONNX Runtime session over the model's cached ONNX export, with inputs and outputs bound to torch tensors."""

    backend = "onnx"
    options = OnnxOptions
    opts: OnnxOptions

    def _setup(self, model: Model) -> None:
        precision, name = self.precision, self.name
        check_onnx_precision(precision, name)
        ort = _import_ort(name)
        self.providers = self._providers(ort)
        cache = OnnxCache(self.cache_dir / "onnx")
        self.artifact: OnnxArtifact = cache.get_or_export(model, precision, self.opts, name)
        try:
            self.session = self._session(ort)
        except _LoadError as e:
            if self.artifact.exported:
                raise
            # A cached file that no longer loads (truncated by a full disk, edited by hand): export it again once.
            log.warning("%s: cached ONNX export %s does not load (%s); exporting again", name, self.artifact.path, e)
            self.artifact = cache.get_or_export(model, precision, self.opts, name, force=True)
            self.session = self._session(ort)
        if precision == "fp16" and self.session.get_providers()[0] == "CPUExecutionProvider":
            log.warning(
                "%s: fp16 on ONNX Runtime's CPU provider: operators without fp16 CPU kernels run in fp32 between "
                "inserted casts; expect fp16-rounded results and no speed-up (fp16 pays off on CUDA/TensorRT)",
                name,
            )
        self._bind()

    # -------------------------------------------------------------------------------------------- set-up
    def _providers(self, ort: Any) -> list[str]:
        available = ort.get_available_providers()
        if self.opts.providers is not None:
            missing = [p for p in self.opts.providers if p not in available]
            if missing or not self.opts.providers:
                raise BackendError(
                    f"{self.name}: backend_options.providers {self.opts.providers} must name providers of this "
                    f"ONNX Runtime installation; not available: {missing}; available: {available}"
                )
            providers = list(self.opts.providers)
        elif self.device.type == "cuda":
            providers = ["CUDAExecutionProvider", "CPUExecutionProvider"]
        else:
            providers = ["CPUExecutionProvider"]
        on_gpu = providers[0] in _GPU_PROVIDERS
        if self.device.type == "cuda" and not on_gpu:
            raise BackendError(
                f"{self.name}: the model is on {self.device} but ONNX Runtime would run it on {providers[0]}; "
                f"put CUDAExecutionProvider or TensorrtExecutionProvider first (available: {available})"
            )
        if self.device.type == "cuda" and providers[0] not in available:
            raise BackendError(
                f"{self.name}: backend 'onnx' on {self.device} needs ONNX Runtime's {providers[0]}, which this "
                f"installation lacks (available: {available}); install onnxruntime-gpu built for your CUDA, or run "
                "this model with backend 'compile' or 'eager'"
            )
        if self.device.type != "cuda" and on_gpu:
            raise BackendError(f"{self.name}: provider {providers[0]} needs a cuda device, the model is on cpu")
        return providers

    def _session(self, ort: Any) -> Any:
        so = ort.SessionOptions()
        so.graph_optimization_level = getattr(ort.GraphOptimizationLevel, _OPT_LEVELS[self.opts.optimization])
        so.intra_op_num_threads = self.opts.intra_op_threads or torch.get_num_threads()
        so.inter_op_num_threads = 1
        so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        so.log_severity_level = 3
        # ONNX Runtime's pool threads spin after each run by default: an idle robot must not burn cores.
        so.add_session_config_entry("session.intra_op.allow_spinning", "0")
        so.add_session_config_entry("session.inter_op.allow_spinning", "0")
        self._stream: torch.cuda.Stream | None = None
        options: list[dict[str, str]] = []
        for p in self.providers:
            opt: dict[str, str] = {}
            if p in _GPU_PROVIDERS and self.device.type == "cuda":
                opt["device_id"] = str(self.device.index or 0)
                stream = torch.cuda.current_stream(self.device)
                # ONNX Runtime reads handle 0 (the legacy default stream) as "no stream given".
                if stream.cuda_stream != 0:
                    opt["user_compute_stream"] = str(stream.cuda_stream)
                    self._stream = stream
                if p == "CUDAExecutionProvider":
                    opt["arena_extend_strategy"] = "kSameAsRequested"
                    # fp32 means fp32, as in PyTorch (which keeps TF32 matmuls off by default).
                    opt["use_tf32"] = "0"
            options.append(opt)
        try:
            session = ort.InferenceSession(
                str(self.artifact.path), sess_options=so, providers=self.providers, provider_options=options
            )
        except Exception as e:
            raise _LoadError(f"{self.name}: ONNX Runtime cannot load {self.artifact.path}: {e}") from e
        # ONNX Runtime falls back to the CPU with only a log line when a GPU provider fails to load.
        if self.providers[0] != "CPUExecutionProvider" and session.get_providers()[0] != self.providers[0]:
            raise BackendError(
                f"{self.name}: ONNX Runtime could not start {self.providers[0]} (CUDA/cuDNN libraries missing or "
                f"mismatched?); the session would run on {session.get_providers()}"
            )
        return session

    def _bind(self) -> None:
        session = self.session
        graph_in = {i.name for i in session.get_inputs()}
        graph_out = {o.name for o in session.get_outputs()}
        unknown = sorted(graph_in - set(self.input_spec))
        missing_out = sorted(set(self.output_spec) - graph_out)
        if unknown or missing_out:
            raise BackendError(
                f"{self.name}: ONNX graph {self.artifact.path} does not fit the model: unknown inputs {unknown}, "
                f"missing outputs {missing_out}"
            )
        self._dev_type = "cuda" if self.device.type == "cuda" else "cpu"
        self._dev_id = self.device.index or 0
        # A model may ignore some declared inputs; an exporter may then drop them from the graph.
        self._in_keys = [k for k in self.input_spec if k in graph_in]
        self._in_meta = {k: (_NUMPY[s.torch_dtype], [1, *s.shape]) for k, s in self.input_spec.items() if k in graph_in}
        n = self.max_batch
        self._staging = {
            k: torch.empty((n, *self.input_spec[k].shape), dtype=self.input_spec[k].torch_dtype, device=self.device)
            for k in self._in_keys
        }
        self._out = {
            k: torch.empty((n, *s.shape), dtype=s.torch_dtype, device=self.device) for k, s in self.output_spec.items()
        }
        self._bindings = []
        for i in range(n):
            binding = session.io_binding()
            for k, t in self._out.items():
                frame = t[i : i + 1]
                binding.bind_output(
                    k, self._dev_type, self._dev_id, _NUMPY[t.dtype], list(frame.shape), frame.data_ptr()
                )
            self._bindings.append(binding)

    # -------------------------------------------------------------------------------------------- run
    def __call__(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        b = self._batch(inputs, self._in_keys or list(self.input_spec))
        staged = {}
        for k in self._in_keys:
            t = inputs[k]
            if t.device != self.device or not t.is_contiguous():
                t = self._staging[k][:b].copy_(t)
            staged[k] = t
        for i in range(b):
            binding = self._bindings[i]
            for k, t in staged.items():
                np_type, shape = self._in_meta[k]
                binding.bind_input(k, self._dev_type, self._dev_id, np_type, shape, t[i].data_ptr())
        if self._dev_type == "cuda":
            cur = torch.cuda.current_stream(self.device)
            if self._stream is None:
                cur.synchronize()  # ONNX Runtime's own stream cannot wait on ours: inputs must be complete
            elif cur != self._stream:
                self._stream.wait_stream(cur)
            for i in range(b):
                self.session.run_with_iobinding(self._bindings[i])
            if self._stream is not None and cur != self._stream:
                cur.wait_stream(self._stream)
        else:
            for i in range(b):
                self.session.run_with_iobinding(self._bindings[i])
        return {k: t[:b] for k, t in self._out.items()}

    def held_bytes(self) -> int:
        """The staging and output buffers; the weights and workspaces are ONNX Runtime's, which PyTorch does not
        see."""
        return tensor_bytes([*self._staging.values(), *self._out.values()])

    def describe(self) -> dict[str, Any]:
        return {
            **super().describe(),
            "providers": self.session.get_providers(),
            "onnx": str(self.artifact.path),
            "exported": self.artifact.exported,
            "opset": self.opts.opset,
            "exporter": self.artifact.manifest.get("exporter"),
        }
