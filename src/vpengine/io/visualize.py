"""Pictures of outputs: colour-mapped depth, segmentation overlays, detection boxes (all BGR uint8, OpenCV order)."""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache
from typing import Any

import numpy as np


@lru_cache(maxsize=8)
def colormap_lut(name: str = "Spectral_r") -> np.ndarray:
    """256x3 uint8 BGR lookup table of a matplotlib colormap (Depth-Anything-V2 draws with Spectral_r)."""
    import matplotlib

    cmap = matplotlib.colormaps[name]
    rgb = (cmap(np.linspace(0, 1, 256))[:, :3] * 255).round().astype(np.uint8)
    return np.ascontiguousarray(rgb[:, ::-1])


def colorize_depth(
    depth: np.ndarray, cmap: str = "Spectral_r", lo: float | None = None, hi: float | None = None
) -> np.ndarray:
    """Min-max scale a float depth (or disparity) map to 0..255 and colour-map it. NaN/inf pixels are black.

    The on-device colour map of the DPT head (``models/dpt.py``) matches this bit for bit; keep the arithmetic
    (float32 scaling, round half to even) the same in both."""
    d = np.asarray(depth, dtype=np.float32)
    finite = np.isfinite(d)
    all_finite = bool(finite.all())
    if not all_finite and not finite.any():
        return np.zeros((*d.shape, 3), np.uint8)
    if lo is None or hi is None:
        valid = d if all_finite else d[finite]
        lo = float(valid.min()) if lo is None else lo
        hi = float(valid.max()) if hi is None else hi
    scaled = np.subtract(d, lo, dtype=np.float32)
    scaled /= np.float32(max(hi - lo, 1e-12))
    if not all_finite:
        scaled[~finite] = 0
    np.clip(scaled, 0, 1, out=scaled)
    scaled *= 255
    idx = np.rint(scaled, out=scaled).astype(np.uint8)
    out = _lookup(colormap_lut(cmap), idx)
    if not all_finite:
        out[~finite] = 0
    return out


def _lookup(table: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``table[idx]`` for an (n, 3) uint8 table: OpenCV's LUT for uint8 indices into 256 entries (several times
    faster than NumPy's gather on a 1080p map), NumPy's ``take`` otherwise (out-of-range indices raise)."""
    if idx.dtype == np.uint8 and len(table) == 256 and idx.ndim == 2 and idx.size:
        import cv2

        return cv2.LUT(cv2.cvtColor(idx, cv2.COLOR_GRAY2BGR), np.ascontiguousarray(table).reshape(256, 1, 3))
    return np.take(table, idx.astype(np.intp, copy=False), axis=0)


def default_palette(n: int, seed: int = 3) -> np.ndarray:
    """n distinct-ish BGR colours (class 0 dark grey)."""
    rng = np.random.default_rng(seed)
    pal = rng.integers(40, 256, (max(n, 1), 3)).astype(np.uint8)
    pal[0] = (60, 60, 60)
    return pal


def overlay_segmentation(
    image: np.ndarray, classes: np.ndarray, palette: np.ndarray | None = None, alpha: float = 0.5
) -> np.ndarray:
    """Blend a class-id map over a BGR image (``(1 - alpha) * image + alpha * colour``, rounded)."""
    import cv2

    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(
            f"overlay_segmentation needs a uint8 (H, W, 3) image, got {image.dtype} {image.shape}"
        )
    n = int(classes.max()) + 1 if classes.size else 1
    pal = np.asarray(
        palette if palette is not None and len(palette) >= n else default_palette(max(n, 256)), np.uint8
    )
    if classes.dtype == np.uint8 and len(pal) != 256:  # ids < n <= len(pal): the table's other rows go unused
        table = np.zeros((256, 3), np.uint8)
        table[: min(len(pal), 256)] = pal[:256]
        pal = table
    colour = _lookup(pal, classes)
    if image.shape[:2] != classes.shape:
        image = cv2.resize(image, (classes.shape[1], classes.shape[0]), interpolation=cv2.INTER_AREA)
    return cv2.addWeighted(image, 1 - alpha, colour, alpha, 0)


def draw_detections(
    image: np.ndarray,
    boxes: np.ndarray,
    scores: np.ndarray,
    labels: np.ndarray,
    names: Sequence[str] | None = None,
) -> np.ndarray:
    """Boxes (x1, y1, x2, y2 in pixels) with 'name score' captions on a copy of a BGR image."""
    import cv2

    out = image.copy()
    pal = default_palette(256)
    for box, score, label in zip(boxes, scores, labels):
        x1, y1, x2, y2 = (round(v) for v in box)
        c = tuple(int(v) for v in pal[int(label) % 256])
        cv2.rectangle(out, (x1, y1), (x2, y2), c, 2)
        name = names[int(label)] if names is not None and 0 <= int(label) < len(names) else str(int(label))
        cv2.putText(
            out,
            f"{name} {score:.2f}",
            (x1, max(12, y1 - 4)),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.45,
            c,
            1,
            cv2.LINE_AA,
        )
    return out


def render_result(result: Any, image: np.ndarray | None = None) -> np.ndarray:
    """One head's ``Result`` as a BGR picture at its frame's size: depth in colour, classes over ``image`` (or
    alone), boxes on ``image`` (or on grey)."""
    out, info = result.outputs, result.info
    h, w = result.frame_size
    if image is not None and image.shape[:2] != (h, w):
        raise ValueError(f"image is {image.shape[1]}x{image.shape[0]}, the result's frame {w}x{h}")
    if "depth_color" in out:
        return np.array(out["depth_color"])
    if "depth" in out:
        return colorize_depth(out["depth"])
    base = image if image is not None else np.full((h, w, 3), 128, np.uint8)
    if "classes" in out:
        pal = info.get("palette")
        return overlay_segmentation(base, out["classes"], None if pal is None else np.asarray(pal, np.uint8))
    if "boxes" in out:
        return draw_detections(base, out["boxes"], out["scores"], out["labels"], info.get("labels"))
    raise ValueError(f"head {result.head!r}: no picture for outputs {sorted(out)}")
