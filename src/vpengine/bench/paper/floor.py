"""The device-time floor: the engine (thread and process mode, frames submitted and frames written in place with
``Engine.frame_slot``) against the same models' device time, measured in one process with CUDA events and CUDA graphs
where they capture.

Three floors: the models each timed alone and summed; the same plus the frame's upload and the results' download
(which any program that wants results on the host pays); the models back to back on one stream, timed as one. A
model that cannot be graph-captured (Faster R-CNN: NMS has data-dependent shapes) is timed eager, launch gaps
included, so a floor with it is generous. Off CUDA there are no device times: only the engine's latencies.

With ``--floor-batches`` (say 1,4,8) the same device times are also taken for batches of that many frames, as an
engine of that many cameras runs them (Note [Cameras] in runtime/worker.py): each model alone, all back to back, and
batches pipelined (``pipelined_ms`` in harness.py: the next batch's backbone beside the last one's heads, each head on
a stream of its own, frames up and results down included), and what a frame costs at that size; and as many sets of
the models, one frame each, pipelined side by side as separate engines of one camera run them (so the largest size
builds that many sets of the models, less one: memory and, on a first run, compile time). The ratio of the two
pipelined figures is what batching buys with no engine's host work on either side. Against ``vpengine bench
cameras``' frames per second they say how far a batched engine and separate engines are from their device time.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from vpengine.bench.paper.harness import KINDS, Bench, InProcess, engines, lockstep, log, pipelined_ms


def check_kinds(kinds: tuple[str, ...]) -> tuple[str, ...]:
    bad = sorted(set(kinds) - set(KINDS))
    if bad or not kinds:
        raise ValueError(f"floor heads {list(kinds)}: accepted are {', '.join(KINDS)} (at least one)")
    return kinds


def run(
    b: Bench, imgs: list[np.ndarray], kinds: tuple[str, ...] = KINDS, batches: tuple[int, ...] = ()
) -> dict[str, Any]:
    heads = [b.head(k, k) for k in check_kinds(kinds)]
    batches = tuple(sorted(set(batches))) if b.on_cuda else ()  # device times: CUDA only (main checks each >= 1)
    # Built for the largest batch, as an engine of that many cameras builds them: the graph of one frame is the
    # same code either way (its own compile, and a capture per batch size)
    seq = InProcess(b, heads, max_batch=max(batches, default=1))
    dt = seq.device_times(imgs[0])
    xfer = seq.transfer_times(imgs[0])
    chained = seq.chained_times(imgs[0])
    by_batch: dict[str, Any] = {}
    # as many more sets of the models as the largest batch has frames, less one: N engines of one camera each
    more = [InProcess(b, heads) for _ in range(max(batches, default=1) - 1)]
    for n in batches:
        times = dt if n == 1 else seq.device_times(imgs[0], batch=n)
        back_to_back = chained["compute"] if n == 1 else seq.back_to_back_ms(imgs[0], n)
        pipelined = pipelined_ms([seq], imgs[:3], n)
        separate = pipelined_ms([seq, *more[: n - 1]], imgs[:3], 1)
        by_batch[str(n)] = {
            "device_ms": times,
            "chained_ms": back_to_back,
            "chained_ms_a_frame": back_to_back / n,
            "pipelined_ms": pipelined,
            "pipelined_ms_a_frame": pipelined / n,
            "separate_pipelined_ms_a_frame": separate / n,
            "batching_gain": separate / pipelined,
        }
        log(
            f"floor, a batch of {n}: "
            + ", ".join(f"{k} {v:.2f}" for k, v in times.items())
            + f" ms; back to back {back_to_back:.2f} ms, {back_to_back / n:.2f} ms a frame; pipelined (the models"
            f" overlapping, transfers included) {pipelined:.2f} ms, {pipelined / n:.2f} ms a frame;"
            f" {n} set{'s' * (n > 1)} of one frame side by side {separate / n:.2f} ms a frame:"
            f" batching buys {separate / pipelined:.2f}x at this schedule"
        )
    del seq, more  # their models' memory goes before the engines start
    out: dict[str, Any] = {"heads": list(kinds), "device_ms": dt, "transfer_ms": xfer, "chained_ms": chained}
    if by_batch:
        out["by_batch"] = by_batch
    if dt:
        out["floor_sum_ms"] = sum(dt.values())
        out["floor_with_transfers_ms"] = out["floor_sum_ms"] + sum(xfer.values())
    for mode in ("thread", "process"):
        with engines([b.config(heads, mode=mode)]) as (eng,):
            out[mode] = lockstep(eng, imgs, b)
            out[f"{mode}_frame_slot"] = lockstep(eng, imgs, b, slot=True)
        if dt:
            for key in (mode, f"{mode}_frame_slot"):
                out[f"{key}_overhead_vs_floor"] = out[key]["mean"] / out["floor_sum_ms"] - 1
                out[f"{key}_overhead_vs_floor_with_transfers"] = out[key]["mean"] / out["floor_with_transfers_ms"] - 1
                out[f"{key}_overhead_vs_chained"] = out[key]["mean"] / chained["compute"] - 1
    floors = (
        f"summed device time {out['floor_sum_ms']:.2f} ms, with transfers {out['floor_with_transfers_ms']:.2f} ms, "
        f"chained {chained['compute']:.2f} ms; "
        if dt
        else ""
    )
    log(
        f"floor ({'+'.join(kinds)}): {floors}engine thread mode {out['thread']['mean']:.2f} ms "
        f"({out['thread_frame_slot']['mean']:.2f} ms from a frame slot), process mode {out['process']['mean']:.2f} ms "
        f"({out['process_frame_slot']['mean']:.2f} ms)"
    )
    return out
