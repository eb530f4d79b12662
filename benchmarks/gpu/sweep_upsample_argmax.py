"""GPU machine: the fused upsample + argmax kernel's time at 1080p (CUDA events, median of 200 launches) for each
block size and warp count, 150 and 21 classes, float16 logits on dinov2_vits14's 37x66 token grid. Writes
$OUT/upsample_argmax_sweep.json; the fastest pair becomes BLOCK / NUM_WARPS in _triton_upsample_argmax.py."""

from __future__ import annotations

import json
import os

import torch

from vpengine.models import _triton_upsample_argmax as kernel


def median_ms(fn, n: int = 200) -> float:
    for _ in range(10):
        fn()
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    times = []
    for _ in range(n):
        start.record()
        fn()
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end))
    return sorted(times)[n // 2]


results = []
for classes in (150, 21):
    logits = torch.randn(1, classes, 37, 66, device="cuda").half()
    out = torch.empty(1080, 1920, dtype=torch.uint8, device="cuda")
    for block in (64, 128, 256, 512, 1024):
        for warps in (1, 2, 4, 8):
            if block < 32 * warps:
                continue
            ms = median_ms(lambda x=logits, o=out, b=block, w=warps: kernel.launch(x, o, b, w))
            results.append({"classes": classes, "block": block, "num_warps": warps, "ms": ms})
            print(f"{classes} classes, block {block}, {warps} warps: {ms:.3f} ms", flush=True)
best = min((r for r in results if r["classes"] == 150), key=lambda r: r["ms"])
print("fastest at 150 classes:", best)
with open(os.path.join(os.environ.get("OUT", "/tmp/out"), "upsample_argmax_sweep.json"), "w") as f:
    json.dump({"device": torch.cuda.get_device_name(), "results": results, "fastest_150": best}, f, indent=1)
