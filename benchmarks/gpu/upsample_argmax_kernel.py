"""GPU machine: the fused upsample + argmax kernels' time at 1080p (CUDA events, median of 200 launches), float16
logits on dinov2_vits14's 37x66 token grid, 150 and 21 classes. Writes into $OUT:

    blocks      upsample_argmax_sweep.json: each block size and warp count, every class searched (the first
                kernel's sweep, which set BLOCK / NUM_WARPS)
    candidates  upsample_argmax_candidates.json: every class searched against each cell's candidates, for noise
                logits (the worst case: many candidates) and smooth ones (a trained head's: a few)
"""

from __future__ import annotations

import json
import os
import sys

import torch
import torch.nn.functional as F

from vpengine.bench.common import event_ms
from vpengine.models import _triton_upsample_argmax as kernel

OUT = os.environ.get("OUT", "/tmp/out")
GRID, FRAME = (37, 66), (1080, 1920)


def median_ms(fn) -> float:  # type: ignore[no-untyped-def]
    return event_ms(fn, 200, warmup=10)


def logits(kind: str, classes: int) -> torch.Tensor:
    if kind == "noise":
        return torch.randn(1, classes, *GRID, device="cuda").half()
    coarse = torch.randn(1, classes, 4, 7, device="cuda") * 4
    fine = F.interpolate(coarse, size=GRID, mode="bilinear", align_corners=False)
    return (fine + 0.05 * torch.randn_like(fine)).half()


def blocks() -> None:
    results = []
    for classes in (150, 21):
        x = logits("noise", classes)
        out = torch.empty(FRAME, dtype=torch.uint8, device="cuda")
        for block in (64, 128, 256, 512, 1024):
            for warps in (1, 2, 4, 8):
                if block < 32 * warps:
                    continue
                ms = median_ms(
                    lambda x=x, o=out, b=block, w=warps: kernel.launch(x, o, b, w, max_candidates=0)
                )
                results.append({"classes": classes, "block": block, "num_warps": warps, "ms": ms})
                print(f"{classes} classes, block {block}, {warps} warps: {ms:.3f} ms", flush=True)
    best = min((r for r in results if r["classes"] == 150), key=lambda r: r["ms"])
    print("fastest at 150 classes:", best)
    with open(os.path.join(OUT, "upsample_argmax_sweep.json"), "w") as f:
        json.dump(
            {"device": torch.cuda.get_device_name(), "results": results, "fastest_150": best}, f, indent=1
        )


def candidates() -> None:
    results = []
    for kind in ("noise", "smooth"):
        for classes in (150, 21):
            x = logits(kind, classes)
            out, every = (torch.empty(FRAME, dtype=torch.uint8, device="cuda") for _ in range(2))
            counts = kernel.launch(x, out)
            kernel.launch(x, every, max_candidates=0)
            row = {
                "logits": kind,
                "classes": classes,
                "same_as_every_class": bool(torch.equal(out, every)),
                "cells_searching_every_class": float((counts < 0).float().mean()),
                "median_candidates": float(counts[counts >= 0].float().median())
                if (counts >= 0).any()
                else None,
                "every_class_ms": median_ms(lambda x=x, o=every: kernel.launch(x, o, max_candidates=0)),
                "candidates_ms": median_ms(lambda x=x, o=out: kernel.launch(x, o)),
            }
            results.append(row)
            print(row, flush=True)
    with open(os.path.join(OUT, "upsample_argmax_candidates.json"), "w") as f:
        json.dump({"device": torch.cuda.get_device_name(), "results": results}, f, indent=1)


for part in sys.argv[1:] or ["candidates"]:
    {"blocks": blocks, "candidates": candidates}[part]()
