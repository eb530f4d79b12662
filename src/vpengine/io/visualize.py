"""Pictures of outputs: colour-mapped depth, segmentation overlays, detection boxes (all BGR uint8, OpenCV order)."""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

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
    """Min-max scale a float depth (or disparity) map to 0..255 and colour-map it. NaN/inf pixels are black."""
    d = np.asarray(depth, dtype=np.float32)
    finite = np.isfinite(d)
    if not finite.any():
        return np.zeros((*d.shape, 3), np.uint8)
    lo = float(d[finite].min()) if lo is None else lo
    hi = float(d[finite].max()) if hi is None else hi
    scaled = np.zeros(d.shape, np.float32)
    np.divide(d - lo, max(hi - lo, 1e-12), out=scaled, where=finite)
    idx = (np.clip(scaled, 0, 1) * 255).round().astype(np.uint8)
    out = colormap_lut(cmap)[idx]
    out[~finite] = 0
    return out


def default_palette(n: int, seed: int = 3) -> np.ndarray:
    """n distinct-ish BGR colours (class 0 dark grey)."""
    rng = np.random.default_rng(seed)
    pal = rng.integers(40, 256, (max(n, 1), 3)).astype(np.uint8)
    pal[0] = (60, 60, 60)
    return pal


def overlay_segmentation(
    image: np.ndarray, classes: np.ndarray, palette: np.ndarray | None = None, alpha: float = 0.5
) -> np.ndarray:
    """Blend a class-id map over a BGR image."""
    n = int(classes.max()) + 1 if classes.size else 1
    pal = palette if palette is not None and len(palette) >= n else default_palette(max(n, 256))
    colour = pal[classes.astype(np.int64)]
    if image.shape[:2] != classes.shape:
        import cv2

        image = cv2.resize(image, (classes.shape[1], classes.shape[0]), interpolation=cv2.INTER_AREA)
    return (image.astype(np.float32) * (1 - alpha) + colour.astype(np.float32) * alpha).astype(np.uint8)


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
