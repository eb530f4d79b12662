"""Pictures of outputs: colour-mapped depth with a colour bar, segmentation overlays, detection boxes, captions on a
background, and one picture of every head side by side (all BGR uint8, OpenCV order).

:func:`draw_result` draws one head's result on its frame; :func:`draw_results` puts the input and every head's
picture side by side (``vpengine predict``, ``vpengine run --video``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from vpengine.colormaps import lut


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
    out = _lookup(lut(cmap), idx)
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
    """n BGR colours, neighbours far apart: hues a golden angle apart at three brightnesses and two saturations (the
    first 16 differ by 60+ in BGR, the first 256 are all different); class 0 is dark grey ('background' in most
    label sets). ``seed`` turns the hue wheel."""
    import cv2

    i = np.arange(max(n, 1))
    # hues a golden angle (0.382 of a turn) apart; OpenCV's hue is 0..180
    hue = ((seed * 0.137 + i * 0.381966) % 1.0) * 180
    sat = np.where((i // 3) % 2 == 0, 235, 170) - 12 * ((i // 6) % 3)  # the later terms keep 256 colours apart
    val = np.array([255, 205, 155])[i % 3] - 12 * ((i // 18) % 3)
    hsv = np.stack([hue, sat, val], -1).astype(np.uint8).reshape(-1, 1, 3)
    pal = np.ascontiguousarray(cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR).reshape(-1, 3))
    pal[0] = (60, 60, 60)
    return pal


def text_scale(image: np.ndarray) -> float:
    """A font scale that reads well on this picture (and still after halving it for a 2x2 mosaic)."""
    return max(0.45, image.shape[0] / 1080 * 1.1)


def caption(
    image: np.ndarray,
    text: str,
    org: tuple[int, int],
    colour: Sequence[int] = (0, 0, 0),
    scale: float | None = None,
) -> tuple[int, int, int, int]:
    """Write ``text`` on a filled box of ``colour`` (the text black or white, whichever reads better), in place.
    ``org`` is the box's top-left corner; the box is moved inside the picture. Returns the box (x1, y1, x2, y2)."""
    import cv2

    scale = text_scale(image) if scale is None else scale
    thick = max(1, round(scale * 1.6))
    th = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)[0][1]
    pad = max(2, round(th * 0.3))
    bw, bh = caption_size(text, scale)
    h, w = image.shape[:2]
    x = min(max(int(org[0]), 0), max(w - bw, 0))
    y = min(max(int(org[1]), 0), max(h - bh, 0))
    bg = tuple(int(c) for c in colour)
    luma = 0.114 * bg[0] + 0.587 * bg[1] + 0.299 * bg[2]
    fg = (0, 0, 0) if luma > 140 else (255, 255, 255)
    cv2.rectangle(image, (x, y), (x + bw, y + bh), bg, -1)
    cv2.putText(image, text, (x + pad, y + pad + th), cv2.FONT_HERSHEY_SIMPLEX, scale, fg, thick, cv2.LINE_AA)
    return x, y, x + bw, y + bh


def caption_size(text: str, scale: float) -> tuple[int, int]:
    """Width and height of :func:`caption`'s box for ``text`` at ``scale``."""
    import cv2

    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, max(1, round(scale * 1.6)))
    pad = max(2, round(th * 0.3))
    return tw + 2 * pad, th + base + 2 * pad


def overlay_segmentation(
    image: np.ndarray, classes: np.ndarray, palette: np.ndarray | None = None, alpha: float = 0.5
) -> np.ndarray:
    """Blend a class-id map over a BGR image (``(1 - alpha) * image + alpha * colour``, rounded)."""
    import cv2

    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"overlay_segmentation needs a uint8 (H, W, 3) image, got {image.dtype} {image.shape}")
    n = int(classes.max()) + 1 if classes.size else 1
    pal = np.asarray(palette if palette is not None and len(palette) >= n else default_palette(max(n, 256)), np.uint8)
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
    """Boxes (x1, y1, x2, y2 in pixels) with 'name score' captions on their class colour, on a copy of a BGR image.
    Each class has its own colour (:func:`default_palette` without its grey). A box of zero width or height (or not
    finite) is not drawn, nor its caption: a caption with no box names nothing (Note [Empty boxes] in engine/boundary.py)."""
    import cv2

    out = image.copy()
    pal = default_palette(256)[1:]
    scale = text_scale(out) * 0.8
    thick = max(2, round(min(out.shape[:2]) / 360))
    for box, score, label in zip(boxes, scores, labels):
        if not (np.isfinite(box).all() and box[2] > box[0] and box[3] > box[1]):
            continue
        x1, y1, x2, y2 = (round(float(v)) for v in box)
        c = tuple(int(v) for v in pal[int(label) % len(pal)])
        cv2.rectangle(out, (x1, y1), (x2, y2), c, thick)
        name = names[int(label)] if names is not None and 0 <= int(label) < len(names) else str(int(label))
        text = f"{name} {float(score):.2f}"
        above = y1 - caption_size(text, scale)[1]  # the caption sits on the box; inside it at the top edge
        caption(out, text, (x1, above if above >= 0 else y1), c, scale)
    return out


def detections(outputs: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A detection head's boxes, scores and labels, only the first ``count`` when the head has fixed capacity."""
    boxes, scores, labels = (_host(outputs[k]) for k in ("boxes", "scores", "labels"))
    if "count" in outputs:
        n = int(_host(outputs["count"]))
        boxes, scores, labels = boxes[:n], scores[:n], labels[:n]
    return boxes.reshape(-1, 4), scores.reshape(-1), labels.reshape(-1)


def depth_picture(depth: np.ndarray, cmap: str = "Spectral_r", bar: bool = True) -> np.ndarray:
    """:func:`colorize_depth` with a colour bar on the right labelled with the map's range (largest at the top)."""
    d = np.asarray(depth, dtype=np.float32)
    finite = d[np.isfinite(d)]
    if not finite.size:
        return colorize_depth(d, cmap)
    lo, hi = float(finite.min()), float(finite.max())
    out = colorize_depth(d, cmap, lo, hi)
    if bar and d.ndim == 2 and min(d.shape) >= 32:
        h, w = d.shape
        bw, bh = max(6, w // 40), max(8, int(h * 0.6))
        x, y = w - bw - max(4, w // 80), (h - bh) // 2
        ramp = np.linspace(255, 0, bh).round().astype(np.uint8)  # top: the largest value
        out[y : y + bh, x : x + bw] = lut(cmap)[ramp][:, None, :]
        out[[y - 1, y + bh], x - 1 : x + bw + 1] = 0
        out[y - 1 : y + bh + 1, [x - 1, x + bw]] = 0
        scale = text_scale(out) * 0.7
        for value, top in ((hi, True), (lo, False)):
            text = f"{value:.3g}"
            tw, th = caption_size(text, scale)
            caption(out, text, (x - tw - 4, y if top else y + bh - th), (0, 0, 0), scale)
    return out


def plane(x: Any, hw: tuple[int, int] | None = None) -> np.ndarray:
    """A map output as its 2-D ``[H, W]`` host array: singleton axes beyond the two spatial ones dropped, so that
    the map has the size ``hw`` when given and it can, else trailing ones first (``[H, W, 1]``), then leading ones
    (``[1, H, W]``). Never ``squeeze()``: that also drops a spatial axis of 1, and a 1xN frame's map came out as a
    vector (a 1x1 frame's as a scalar)."""
    a = _host(x)
    if hw is not None and a.ndim > 2 and [n for n in a.shape if n != 1] == [n for n in hw if n != 1]:
        return a.reshape(hw)
    while a.ndim > 2 and a.shape[-1] == 1:
        a = a[..., 0]
    while a.ndim > 2 and a.shape[0] == 1:
        a = a[0]
    return a


#: The outputs each kind of head is drawn and written from, any one set of them (Note [Kinds and outputs]): a depth
#: head's map, or only its colour picture (postprocess output: colormap)
KIND_OUTPUTS = {
    "depth": ({"depth"}, {"depth_color"}),
    "segmentation": ({"classes"},),
    "detection": ({"boxes", "scores", "labels"},),
}


def has_kind_outputs(kind: str, outputs: set[str]) -> bool:
    """Whether ``outputs`` hold what a head of ``kind`` is drawn and written from (any kind not listed: yes)."""
    return any(need <= outputs for need in KIND_OUTPUTS.get(kind, (set(),)))


def head_kind(info: Mapping[str, Any]) -> str:
    """What a head produces, from its metadata (``kind``) or its output names: depth, segmentation, detection or
    generic.

    Note [Kinds and outputs]
    ~~~~~~~~~~~~~~~~~~~~~~~~
    A kind is drawn and written from its outputs of fixed names (KIND_OUTPUTS). A head whose ``meta["kind"]`` says
    one without those outputs (a user head modelled on a zoo head, its map named ``mask``) is a generic head, so its
    outputs are written as ``.npz`` rather than lost or crashing the run's writer; planning warns of it. A head that
    declares no kind is taken by its output names."""
    outs = set(info.get("outputs", {}))
    declared = info.get("kind")
    if declared:  # with the outputs it is made from (or none known to check): that kind; without them: generic
        return str(declared) if not outs or has_kind_outputs(str(declared), outs) else "generic"
    if "depth" in outs:
        return "depth"
    if "classes" in outs:
        return "segmentation"
    if {"boxes", "scores", "labels"} <= outs:
        return "detection"
    return "generic"


def draw_result(
    frame: np.ndarray | None,
    outputs: Mapping[str, Any] | Any,
    info: Mapping[str, Any] | None = None,
    title: str | None = None,
) -> np.ndarray:
    """One head's result drawn on its frame (BGR uint8 HxWx3): depth colour-mapped with a colour bar,
    segmentation over the frame with its most frequent classes named, detection boxes with captions; anything
    else as the frame with its output names. ``outputs``: a :class:`~vpengine.engine.Result` or its dict;
    ``info``: the head's ``Engine.head_info`` (kind, labels, palette); ``title``: a caption at the top left.
    Dense maps of another size than the frame are resized to it (boxes are taken to be in the frame's pixels)."""
    import cv2

    out = getattr(outputs, "outputs", outputs)
    info = info if info is not None else {"outputs": dict(out)}
    kind = head_kind(info)
    size = None if frame is None else frame.shape[:2]
    names = info.get("labels")
    if kind == "depth" and "depth" in out:
        d = plane(out["depth"], size).astype(np.float32, copy=False)
        if size is not None and d.shape != size:
            d = cv2.resize(d, (size[1], size[0]), interpolation=cv2.INTER_LINEAR)
        pic = depth_picture(d)
    elif kind == "segmentation" and "classes" in out:
        classes = plane(out["classes"], size)
        if size is not None and classes.shape != size:  # nearest: class ids are not numbers to blend
            rows = np.arange(size[0]) * classes.shape[0] // size[0]
            cols = np.arange(size[1]) * classes.shape[1] // size[1]
            classes = classes[rows[:, None], cols[None, :]]
        base = frame if frame is not None else np.zeros((*classes.shape, 3), np.uint8)
        pal_meta = info.get("palette")
        n = int(classes.max(initial=0)) + 1
        pal = np.asarray(pal_meta, np.uint8) if pal_meta is not None and len(pal_meta) >= n else None
        pic = overlay_segmentation(base, classes, pal)
        used = pal if pal is not None else default_palette(max(n, 256))
        counts = np.bincount(classes.ravel().astype(np.intp, copy=False))  # 7x faster than np.unique
        y = _title_height(pic, title)
        largest = np.argsort(-counts, kind="stable")[: min(6, int((counts > 0).sum()))]
        for cid in largest:  # a legend of the largest classes, each on its colour
            label = names[int(cid)] if names is not None and 0 <= int(cid) < len(names) else str(int(cid))
            y = caption(pic, label, (4, y), used[int(cid)], text_scale(pic) * 0.7)[3] + 2
    elif kind == "detection" and {"boxes", "scores", "labels"} <= set(out):
        base = frame if frame is not None else np.zeros((480, 640, 3), np.uint8)
        pic = draw_detections(base, *detections(out), names)
    else:
        base = frame if frame is not None else np.zeros((480, 640, 3), np.uint8)
        pic = base.copy()
        caption(pic, "outputs: " + ", ".join(out), (4, _title_height(pic, title)))
    if title:
        caption(pic, title, (0, 0))
    return pic


def draw_results(
    frame: np.ndarray,
    results: Mapping[str, Mapping[str, Any] | Any | None],
    infos: Mapping[str, Mapping[str, Any]] | None = None,
    max_width: int = 1920,
) -> np.ndarray:
    """The input and every head's picture (:func:`draw_result`) side by side in one BGR picture: one row for up to
    three pictures, else a grid about as wide as high, at most ``max_width`` pixels across (small frames are shown
    larger, up to 360 pixels high, so that captions stay readable). ``results``: head name -> its result (None: 'no
    result yet'); ``infos``: head name -> ``Engine.head_info``."""
    import cv2

    infos = infos or {}
    h, w = frame.shape[:2]
    n = 1 + len(results)
    cols = n if n <= 3 else math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    scale = min(max_width / (cols * w), max(1.0, 360 / h))
    th, tw = max(1, round(h * scale)), max(1, round(w * scale))
    # every picture is drawn at its final size (captions drawn big and then shrunk would be unreadable)
    small = frame if (th, tw) == (h, w) else cv2.resize(frame, (tw, th), interpolation=_interpolation(scale))
    tiles = [small.copy()]
    caption(tiles[0], "input", (0, 0))
    for head, result in results.items():
        if result is None:
            tile = small // 3
            caption(tile, f"{head}: no result yet", (0, 0))
        else:
            tile = draw_result(small, _boxes_scaled(result, tw / w, th / h), infos.get(head), head)
        tiles.append(tile)
    mosaic = np.zeros((rows * th, cols * tw, 3), np.uint8)
    for k, tile in enumerate(tiles):
        r, c = divmod(k, cols)
        mosaic[r * th : (r + 1) * th, c * tw : (c + 1) * tw] = tile
    return mosaic


def _boxes_scaled(result: Mapping[str, Any] | Any, sx: float, sy: float) -> Mapping[str, Any]:
    """A result's outputs with its boxes (frame pixels) in the pixels of the frame scaled by (sx, sy)."""
    out = getattr(result, "outputs", result)
    if "boxes" not in out or (sx, sy) == (1.0, 1.0):
        return out
    return {**out, "boxes": _host(out["boxes"]) * np.array([sx, sy, sx, sy], np.float32)}


def _interpolation(scale: float) -> int:
    import cv2

    return cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR


def _title_height(image: np.ndarray, title: str | None) -> int:
    """Where text under a title caption may start."""
    return caption_size(title, text_scale(image))[1] + 2 if title else 0


def _host(x: Any) -> np.ndarray:
    """A numpy array of a host array or a (device, bfloat16) torch tensor."""
    if type(x).__module__.startswith("torch"):
        t = x.detach().cpu()
        if t.is_floating_point() and t.dtype.itemsize < 4:
            t = t.float()
        return np.asarray(t.numpy())
    return np.asarray(x)
