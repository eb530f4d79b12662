"""The compile backend on CUDA: torch.compile replayed as CUDA graphs over static buffers, one per batch size (Note
[CUDA graphs]), and the ONNX backend on the CUDA provider. Run on the GPU machine: ``pytest -m gpu tests/gpu``.

What must hold for a long-running robot process: same results as eager (fp32 tolerance), no device memory
allocated by a replay, outputs copied out of the static buffers stay intact when the next frame replays, replays
ordered on the caller's stream, and a model that cannot be captured fails at warm-up with the fix in the message.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from helpers.frames import frame
from helpers.models import SmallHead
from tests_paths import tiny
from vpengine.backends import BackendError, make_executor
from vpengine.backends.base import tensor_bytes
from vpengine.backends.compiled import CompiledExecutor
from vpengine.engine import Engine
from vpengine.models.base import Model
from vpengine.models.build import build_model
from vpengine.runtime.plan import make_plan

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.timeout(900),
    pytest.mark.usefixtures("require_cuda", "inductor_in_process"),
]

CUDA = torch.device("cuda")
TINY_MODELS = ["foundation", "depth", "seg", "det"]
THRESHOLD = 0.5  # tiny_det's default score threshold


def build(cfg, name: str) -> Model:
    plan = make_plan(cfg)
    if name == "foundation":
        return build_model(cfg, name, "foundation", plan.frame_spec, {}, CUDA, plan_only=False)
    return build_model(cfg, name, "head", plan.features, plan.feature_meta, CUDA, plan_only=False)


def inputs_for(cfg, name: str, i: int) -> dict[str, torch.Tensor]:
    """Frame ``i`` on the GPU for the foundation model; its (eager) features for a head; a batch of one. Fresh
    tensors each time."""
    h, w = cfg.input.height, cfg.input.width
    x = {"frame": torch.from_numpy(frame(i, h, w))[None].to(CUDA)}
    if name == "foundation":
        return x
    precision = cfg.foundation_model.precision or cfg.precision
    feats = make_executor(build(cfg, "foundation"), "eager", CUDA, "foundation", precision=precision)(x)
    return {k: feats[k].clone() for k in build(cfg, name).input_spec}


def snapshot(out: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in out.items()}


def assert_same_results(name: str, got: dict, want: dict, rtol: float, what: str) -> None:
    """Floats within ``rtol`` of the output's scale; class maps up to argmax near-ties; confident detections equal."""
    assert set(got) == set(want), what
    for k, w in want.items():
        g = got[k]
        assert g.dtype == w.dtype and g.shape == w.shape, f"{what}: {k}"
        if w.dtype.is_floating_point:
            scale = w.float().abs().max().item()
            torch.testing.assert_close(g, w, rtol=rtol, atol=rtol * scale, msg=lambda m, k=k: f"{what}: {k}: {m}")
    if name == "seg":
        differ = (got["classes"] != want["classes"]).float().mean().item()
        assert differ <= 1e-3, f"{what}: {differ:.3%} of pixels differ"
    if name == "det":

        def confident(d):
            keep = d["scores"] > THRESHOLD + 1e-3
            return sorted(zip(map(tuple, d["boxes"][keep].tolist()), d["labels"][keep].tolist()))

        assert confident(got) == confident(want), what


# ------------------------------------------------------------------------------------------ correctness
@pytest.mark.parametrize("name", TINY_MODELS)
def test_compiled_cuda_graph_matches_eager(name):
    cfg = tiny("thread", "device=cuda")
    ex = make_executor(build(cfg, name), "compile", CUDA, name)
    assert ex.describe()["cudagraphs"] is True
    eager = make_executor(build(cfg, name), "eager", CUDA, name)
    worker = torch.cuda.Stream()
    for i in range(3):
        x = inputs_for(cfg, name, i)
        with torch.cuda.stream(worker):
            worker.wait_stream(torch.cuda.default_stream())
            got = snapshot(ex(x))
        worker.synchronize()
        assert_same_results(name, got, snapshot(eager(x)), 1e-4, f"{name} frame {i}")


@pytest.mark.parametrize("precision", ["fp16", "bf16"])
def test_compiled_cuda_graph_at_low_precision_stays_close_to_fp32(precision):
    cfg32, cfg = tiny("thread", "device=cuda"), tiny("thread", "device=cuda", f"precision={precision}")
    x32, x = inputs_for(cfg32, "foundation", 0), inputs_for(cfg, "foundation", 0)
    want = snapshot(make_executor(build(cfg32, "foundation"), "eager", CUDA, "foundation")(x32))
    ex = make_executor(build(cfg, "foundation"), "compile", CUDA, "foundation", precision=precision)
    assert ex.describe()["cudagraphs"] is True
    got = snapshot(ex(x))
    dtype = {"fp16": torch.float16, "bf16": torch.bfloat16}[precision]
    tol = {"fp16": 1e-2, "bf16": 5e-2}[precision]
    for k, w in want.items():
        assert got[k].dtype == dtype
        scale = w.abs().max().item()
        assert (got[k].float() - w).abs().max().item() <= tol * scale, k


@pytest.mark.parametrize("name", ["foundation", "seg"])
def test_one_cuda_graph_per_batch_size_each_frame_as_if_alone(name, monkeypatch):
    """A graph per batch size 1..max_batch, captured at warm-up: a batch of B frames gives each frame what a batch of
    one gives it and what eager gives, in any order of sizes, and no replay allocates (one pool for all sizes).
    cuDNN may pick a TF32 algorithm for the patch embedding's convolution at one batch size and not at another
    (PyTorch allows TF32 convolutions by default), a difference of about 3e-4 of the features' scale that has
    nothing to do with batching: the comparison runs with TF32 off."""
    monkeypatch.setattr(torch.backends.cudnn, "allow_tf32", False)
    cfg = tiny("thread", "device=cuda")
    worker = torch.cuda.Stream()
    with torch.cuda.stream(worker):
        ex = make_executor(build(cfg, name), "compile", CUDA, name, max_batch=3)
    assert ex.describe()["cudagraphs"] is True and sorted(ex._graphs) == [1, 2, 3]
    eager = make_executor(build(cfg, name), "eager", CUDA, name)
    xs = [inputs_for(cfg, name, i) for i in range(3)]
    batches = {n: {k: torch.cat([x[k] for x in xs[:n]]) for k in xs[0]} for n in (1, 2, 3)}
    alone = []
    for x in xs:
        with torch.cuda.stream(worker):
            worker.wait_stream(torch.cuda.default_stream())
            alone.append(snapshot(ex(x)))
    worker.synchronize()
    for n in (3, 1, 2, 3):
        torch.cuda.synchronize()
        allocated = torch.cuda.memory_allocated()
        with torch.cuda.stream(worker):
            out = ex(batches[n])
        worker.synchronize()
        assert torch.cuda.memory_allocated() == allocated, f"a batch of {n} allocated"
        got = snapshot(out)
        for i in range(n):
            frame_i = {k: v[i : i + 1] for k, v in got.items()}
            assert_same_results(name, frame_i, alone[i], 1e-5, f"{name} frame {i} of {n}")
            assert_same_results(name, frame_i, snapshot(eager(xs[i])), 1e-4, f"{name} frame {i} of {n} vs eager")


# ------------------------------------------------------------------------------------------ memory and buffers
def test_replays_allocate_no_device_memory():
    """200 frames through every tiny model from rotating 'mailbox slots': allocated and reserved memory stay flat."""
    cfg = tiny("thread", "device=cuda")
    worker = torch.cuda.Stream()
    executors = {}
    with torch.cuda.stream(worker):
        for name in TINY_MODELS:
            executors[name] = make_executor(build(cfg, name), "compile", CUDA, name)
    # Three preallocated input slots and one output slot per model, as the mailboxes hold them.
    slots = {n: [inputs_for(cfg, n, i) for i in range(3)] for n in TINY_MODELS}
    outs = {
        n: {k: torch.empty((1, *s.shape), dtype=s.torch_dtype, device=CUDA) for k, s in ex.output_spec.items()}
        for n, ex in executors.items()
    }
    with torch.cuda.stream(worker):
        for n, ex in executors.items():  # one call each outside the measurement, like the worker's warm-up
            ex(slots[n][0])
    torch.cuda.synchronize()
    allocated, reserved = torch.cuda.memory_allocated(), torch.cuda.memory_reserved()
    with torch.cuda.stream(worker), torch.inference_mode():
        for i in range(200):
            for n, ex in executors.items():
                result = ex(slots[n][i % 3])
                for k, t in outs[n].items():
                    t.copy_(result[k], non_blocking=True)
    torch.cuda.synchronize()
    assert torch.cuda.memory_allocated() == allocated
    assert torch.cuda.memory_reserved() == reserved


def test_the_graphs_of_every_batch_size_take_about_the_largest_ones_pool():
    """Note [CUDA graphs]: the graphs of batches 1..4 of the depth head at 1080p (the shipped GPU config's, fp16)
    share a pool about as big as the batch of 4 alone needs, and held_bytes counts it. Captured smallest first they
    took far more (docs/benchmarks.md)."""
    from helpers import heads

    cfg = heads.head_config((1080, 1920), {"name": "depth", "model": "dav2_depth_s"}, device="cuda")
    ex = make_executor(
        heads.build_head(cfg, (37, 66), 384, "cuda", "float16"), "compile", CUDA, "depth", precision="fp16", max_batch=4
    )
    pools = {tuple(g.pool()) for g in ex._graphs.values()}
    assert len(pools) == 1  # one pool for every batch size
    shared = ex.held_bytes() - tensor_bytes([*ex.model.parameters(), *ex.model.buffers(), *ex._static[4].values()])
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    before = torch.cuda.memory_reserved()
    alone = torch.cuda.CUDAGraph()
    with torch.inference_mode(), torch.cuda.graph(alone):
        ex._run(ex._static[4])
    largest = torch.cuda.memory_reserved() - before  # a capture's pool takes new segments only
    print(
        f"depth head, 1080p, fp16: batches 1-4 {shared / 2**20:.0f} MiB, the batch of 4 alone {largest / 2**20:.0f} MiB"
    )
    assert 0.9 * largest <= shared <= 1.1 * largest


def test_copied_outputs_survive_the_next_replay():
    """Note [Executor contract]: a copy taken after frame A is intact after frame B replays into the same buffers."""
    cfg = tiny("thread", "device=cuda")
    ex = make_executor(build(cfg, "depth"), "compile", CUDA, "depth")
    eager = make_executor(build(cfg, "depth"), "eager", CUDA, "depth")
    a, b = inputs_for(cfg, "depth", 0), inputs_for(cfg, "depth", 1)
    slot_a = torch.empty((1, *ex.output_spec["depth"].shape), device=CUDA)
    slot_b = torch.empty_like(slot_a)
    out_a = ex(a)
    slot_a.copy_(out_a["depth"])
    out_b = ex(b)
    slot_b.copy_(out_b["depth"])
    torch.cuda.synchronize()
    want_a, want_b = eager(a)["depth"].clone(), eager(b)["depth"].clone()
    assert_same_results("depth", {"depth": slot_a}, {"depth": want_a}, 1e-4, "A's copy after B")
    assert_same_results("depth", {"depth": slot_b}, {"depth": want_b}, 1e-4, "B")
    assert not torch.allclose(want_a, want_b)  # the two frames really differ
    assert out_a["depth"].data_ptr() == out_b["depth"].data_ptr()  # ... through the same static buffer


def test_replay_is_ordered_on_the_callers_stream():
    """Inputs written late on the worker's stream (after a long kernel) are what the replay reads."""
    cfg = tiny("thread", "device=cuda")
    worker = torch.cuda.Stream()
    with torch.cuda.stream(worker):
        ex = make_executor(build(cfg, "depth"), "compile", CUDA, "depth")
    eager = make_executor(build(cfg, "depth"), "eager", CUDA, "depth")
    a, b = inputs_for(cfg, "depth", 0), inputs_for(cfg, "depth", 1)
    slot = {k: v.clone() for k, v in a.items()}
    out = torch.empty((1, *ex.output_spec["depth"].shape), device=CUDA)
    torch.cuda.synchronize()
    with torch.cuda.stream(worker):
        torch.cuda._sleep(200_000_000)  # ~0.1 s of GPU time before the slot is refilled with frame B
        for k, t in slot.items():
            t.copy_(b[k])
        out.copy_(ex(slot)["depth"])
    worker.synchronize()
    assert_same_results("depth", {"depth": out}, {"depth": eager(b)["depth"].clone()}, 1e-4, "late input")


# ------------------------------------------------------------------------------------------ slot-bound runs
@pytest.mark.parametrize("name", ["foundation", "depth"])
def test_slot_bound_runs_read_and_write_the_slots_they_are_told(name):
    """Note [Slot-bound runs]: run_bound(i, j) reads input slot i and writes output slot j, page-locked host slots
    included (the foundation's frames, host outputs), with what a call would give, and allocates nothing."""
    cfg = tiny("thread", "device=cuda")
    worker = torch.cuda.Stream()
    with torch.cuda.stream(worker):
        ex = make_executor(build(cfg, name), "compile", CUDA, name)
    eager = make_executor(build(cfg, name), "eager", CUDA, name)
    on_host = name == "foundation"  # frames come from host mailboxes; the depth head's outputs go to one
    batches = [inputs_for(cfg, name, i) for i in range(3)]
    ins = [{k: v[0] for k, v in x.items()} for x in batches]  # a slot holds one frame: no batch dimension
    if on_host:
        ins = [{k: v.cpu().pin_memory() for k, v in x.items()} for x in ins]
    outs = [
        {
            k: torch.empty(s.shape, dtype=s.torch_dtype, device="cpu" if not on_host else CUDA)
            for k, s in ex.output_spec.items()
        }
        for _ in range(2)
    ]
    if not on_host:
        outs = [{k: v.pin_memory() for k, v in o.items()} for o in outs]
    with torch.cuda.stream(worker):
        assert ex.bind(ins, outs) is True
    assert ex.describe()["slot_bound"] is True
    for i, j in [(0, 1), (2, 0), (1, 1), (0, 0)]:
        torch.cuda.synchronize()
        allocated = torch.cuda.memory_allocated()
        with torch.cuda.stream(worker), torch.inference_mode():
            ex.run_bound(i, j)
        worker.synchronize()
        assert torch.cuda.memory_allocated() == allocated, f"slot {i} -> {j} allocated"
        want = snapshot(eager(batches[i]))
        got = {k: v.to(CUDA)[None] for k, v in outs[j].items()}
        assert_same_results(name, got, want, 1e-4, f"{name} slot {i} -> {j}")


def test_a_run_launched_from_another_thread_is_queued_on_the_workers_stream():
    """Note [Launch path]: run_bound_on(stream, i, j), called from a thread whose current stream is another one (the
    submitting thread of Note [Inline launch]), queues the three graphs on ``stream`` with raw cudaGraphLaunch calls:
    ordered after what that stream already holds (here a delay, then the write of the input slot), the results of
    run_bound, nothing allocated, and the calling thread's current stream untouched."""
    cfg = tiny("thread", "device=cuda")
    worker = torch.cuda.Stream()
    with torch.cuda.stream(worker):
        ex = make_executor(build(cfg, "depth"), "compile", CUDA, "depth")
    eager = make_executor(build(cfg, "depth"), "eager", CUDA, "depth")
    feats = [inputs_for(cfg, "depth", i) for i in range(2)]
    ins = [{k: torch.zeros_like(v[0]) for k, v in feats[0].items()}]  # one slot, one frame
    outs = [{k: torch.empty(s.shape, dtype=s.torch_dtype).pin_memory() for k, s in ex.output_spec.items()}]
    with torch.cuda.stream(worker):
        assert ex.bind(ins, outs) is True
    assert ex.describe()["raw_launch"] is True
    mine = torch.cuda.current_stream()
    assert mine != worker
    for i in (1, 0):
        torch.cuda.synchronize()
        allocated = torch.cuda.memory_allocated()
        with torch.cuda.stream(worker):
            torch.cuda._sleep(50_000_000)  # ~25 ms, then this frame's features land in the input slot
            for k, v in feats[i].items():
                ins[0][k].copy_(v[0])
        ex.run_bound_on(worker, 0, 0)
        assert torch.cuda.current_stream() == mine
        worker.synchronize()
        assert torch.cuda.memory_allocated() == allocated
        want = snapshot(eager(feats[i]))
        assert_same_results("depth", {k: v.to(CUDA)[None] for k, v in outs[0].items()}, want, 1e-4, f"frame {i}")
        for v in ins[0].values():
            v.zero_()


class _Noisy(SmallHead):
    """A head that adds random noise: its CUDA graph draws from the CUDA generator on every replay."""

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {"y": inputs["x"] + torch.rand_like(inputs["x"])}


def test_a_graph_that_draws_random_numbers_is_never_launched_raw():
    """A raw launch would replay the same random numbers every frame (replay advances the generator, a raw launch
    does not): such a model's runs from another thread switch streams and replay instead, and still differ."""
    ex = make_executor(_Noisy().to(CUDA), "compile", CUDA, "noisy")
    ins = [{"x": torch.zeros(4, 8, device=CUDA)}]
    outs = [{"y": torch.empty(4, 8, device=CUDA)}]
    assert ex.bind(ins, outs) is True
    assert ex.describe()["raw_launch"] is False
    worker = torch.cuda.Stream()
    draws = []
    for _ in range(2):
        ex.run_bound_on(worker, 0, 0)
        worker.synchronize()
        draws.append(outs[0]["y"].clone())
    assert not torch.equal(draws[0], draws[1])


def test_a_slot_that_cannot_be_bound_leaves_the_executor_running_unbound():
    """Pageable host slots cannot be copied inside a CUDA graph: bind says no and calls keep working."""
    cfg = tiny("thread", "device=cuda")
    ex = make_executor(build(cfg, "foundation"), "compile", CUDA, "foundation")
    pageable = [{k: v[0].cpu() for k, v in inputs_for(cfg, "foundation", 0).items()}]
    outs = [{k: torch.empty(s.shape, dtype=s.torch_dtype, device=CUDA) for k, s in ex.output_spec.items()}]
    assert ex.bind(pageable, outs) is False
    assert ex.describe()["slot_bound"] is False
    x = inputs_for(cfg, "foundation", 1)
    eager = make_executor(build(cfg, "foundation"), "eager", CUDA, "foundation")
    assert_same_results("foundation", snapshot(ex(x)), snapshot(eager(x)), 1e-4, "after a failed bind")
    torch.randn(3, device=CUDA)  # the CUDA generator is out of capture mode


# ------------------------------------------------------------------------------------------ failures
class _HostSync(SmallHead):
    """A head that reads a value back to the host mid-forward (.item()): legal eagerly, not inside a CUDA graph."""

    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        x = inputs["x"] * 2
        return {"y": x + x.max().item()}


def test_a_model_that_cannot_be_captured_fails_at_warm_up_with_the_fix():
    opts = {"fullgraph": False}
    with pytest.raises(BackendError, match=r"(?s)user: CUDA graph capture \(batch of 1\) failed.*cudagraphs: false"):
        make_executor(_HostSync().to(CUDA), "compile", CUDA, "user", options=opts)
    ex = make_executor(_HostSync().to(CUDA), "compile", CUDA, "user", options={**opts, "cudagraphs": False})
    assert ex.describe()["cudagraphs"] is False
    x = {"x": torch.randn(1, 4, 8, device=CUDA)}
    torch.testing.assert_close(ex(x)["y"], x["x"] * 2 + (x["x"] * 2).max())


class _Doubling(SmallHead):
    def forward(self, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {"y": inputs["x"] * 2}


def test_compile_and_capture_report_each_batch_size_as_steps():
    """Note [Start progress]: each batch size run (twice), then each graph captured, is a step of the set-up."""
    steps: list[tuple[int, int]] = []
    make_executor(_Doubling().to(CUDA), "compile", CUDA, "user", max_batch=3, progress=lambda *s: steps.append(s))
    assert steps == [(i, 9) for i in range(1, 10)]


def test_a_capture_out_of_device_memory_says_so_and_names_the_batch(monkeypatch):
    """The largest batch is captured first, so it is where a full device shows: the error names that batch and
    what to change, not a host sync."""

    class _Full:
        def __init__(self, *args: object, **kwargs: object) -> None:
            pass

        def __enter__(self) -> None:
            raise torch.cuda.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB")

        def __exit__(self, *exc: object) -> None:
            return None

    compile_first = CompiledExecutor._compile

    def compile_then_fill(self: CompiledExecutor) -> None:
        compile_first(self)  # the device fills once the model has compiled, as it would at capture
        monkeypatch.setattr(torch.cuda, "graph", _Full)

    monkeypatch.setattr(CompiledExecutor, "_compile", compile_then_fill)
    with pytest.raises(
        BackendError, match=r"(?s)capture \(batch of 3\) failed.*too little free memory for a batch of 3"
    ):
        make_executor(_Doubling().to(CUDA), "compile", CUDA, "user", max_batch=3)


# ------------------------------------------------------------------------------------------ ONNX on CUDA
def test_onnx_on_cuda_runs_on_the_cuda_provider_or_says_what_is_missing(tmp_path):
    import onnxruntime as ort

    cfg = tiny("thread", "device=cuda")
    if "CUDAExecutionProvider" not in ort.get_available_providers():
        with pytest.raises(BackendError, match=r"needs ONNX Runtime's CUDAExecutionProvider.*onnxruntime-gpu"):
            make_executor(build(cfg, "foundation"), "onnx", CUDA, "foundation", cache_dir=tmp_path)
        return
    worker = torch.cuda.Stream()
    with torch.cuda.stream(worker):  # as in a worker: ONNX Runtime is handed the worker's stream
        ex = make_executor(build(cfg, "foundation"), "onnx", CUDA, "foundation", cache_dir=tmp_path)
    assert ex.describe()["providers"][0] == "CUDAExecutionProvider"
    eager = make_executor(build(cfg, "foundation"), "eager", CUDA, "foundation")
    slots = [inputs_for(cfg, "foundation", i) for i in range(3)]
    torch.cuda.synchronize()
    for i, x in enumerate(slots):
        with torch.cuda.stream(worker):
            got = snapshot(ex(x))
        worker.synchronize()
        assert_same_results("foundation", got, snapshot(eager(x)), 1e-3, f"onnx cuda frame {i}")
    torch.cuda.synchronize()
    free = torch.cuda.mem_get_info()[0]  # after warm-up ONNX Runtime's arena holds what a run needs
    with torch.cuda.stream(worker):
        for i in range(100):
            ex(slots[i % 3])
    worker.synchronize()
    assert torch.cuda.mem_get_info()[0] == free


# ------------------------------------------------------------------------------------------ in the engine
@pytest.mark.parametrize("mode", ["thread", "process"])
def test_engine_with_compiled_models_on_cuda_matches_eager(mode):
    """Every model compiled and graph-captured, concurrently in worker threads or processes, on their own streams."""
    compiled = [f"heads.{h}.backend=compile" for h in ("depth", "seg", "det")]
    runs = {}
    # compiled models run from graphs bound to the slots (Note [Slot-bound runs])
    slot_bound = ["foundation_model.backend=compile", *compiled]
    for label, extra in (("eager", []), ("compile", slot_bound)):
        cfg = tiny(mode, "device=cuda", *extra)
        out = {}
        with Engine(cfg) as e:
            for i in range(5):
                fid = e.submit(frame(i), frame_id=i)
                res = e.wait(fid, timeout=120)
                assert set(res) == {"depth", "seg", "det"}, (label, i, sorted(res))
                out[i] = {h: r.outputs for h, r in res.items()}
            assert all(m["errors"] == 0 for m in e.stats()["models"].values())
        runs[label] = out
    for i in range(5):
        got, want = runs["compile"][i], runs["eager"][i]
        scale = np.abs(want["depth"]["depth"]).max()
        np.testing.assert_allclose(got["depth"]["depth"], want["depth"]["depth"], rtol=1e-4, atol=1e-4 * scale)
        assert (got["seg"]["classes"] != want["seg"]["classes"]).mean() <= 1e-3
        keep_g = got["det"]["scores"] > THRESHOLD + 1e-3
        keep_w = want["det"]["scores"] > THRESHOLD + 1e-3
        np.testing.assert_allclose(got["det"]["boxes"][keep_g], want["det"]["boxes"][keep_w])


def test_compiled_faster_rcnn_on_cuda_never_recompiles_once_warm_whatever_the_batch_and_box_count():
    """tests/unit/test_backends.py checks the guards with aot_eager on the CPU; here inductor compiles the detector on
    CUDA, as a GPU engine does: once warm, no batch size or box count recompiles (Note [RoIAlign runs eagerly])."""
    cfg = tiny(
        "thread",
        "device=cuda",
        "heads.det.model=frcnn_dinov2_lite",
        "heads.det.options={num_classes: 3}",
        "weights.random_weights=true",
    )
    model = build(cfg, "det")
    ex = make_executor(model, "compile", CUDA, "det", options={"fullgraph": False, "cudagraphs": False}, max_batch=2)
    g = torch.Generator().manual_seed(0)
    with torch.compiler.set_stance("fail_on_recompile"):
        for i, (b, scale) in enumerate([(1, 1.0), (2, 4.0), (1, 0.1), (2, 0.5), (1, 8.0), (2, 2.0)]):
            x = {k: (torch.randn((b, *s.shape), generator=g) * scale).to(CUDA) for k, s in model.input_spec.items()}
            out = ex(x)
            assert out["count"].shape == (b,), f"frame {i}"
