"""The boundary: one door in, one door out, for every frame whatever door it came through.

``Engine.submit``, ``Engine.frame_slot`` and ``Engine.predict`` bring frames in through :meth:`Boundary.write`, and
every result leaves through :meth:`Boundary.to_frame`; ``vpengine run``/``predict``, the ROS 2 bridge, bags and the
web view only ever use those engine calls, so none of them resizes anything on its own.

Note [Frame grid]
~~~~~~~~~~~~~~~~~
The models are built, compiled and captured for one input size, the config's ``input.height`` x ``input.width``
(the *canvas*): the mailboxes, CUDA graphs and full-resolution outputs all have that size, allocated once at start.
A frame of any other size (up to ``input.max_frame_side``) is scaled to fit the canvas with its aspect ratio kept (never
stretched; area-averaged when shrunk to half or less, else bilinear, as below) and centred; the band around it is filled
with the normalisation mean, which is zero once normalised. Its outputs come back in the frame's own pixel grid: dense
maps are cut out of the canvas and resized to the frame's size (values bilinear, or area-averaged when shrunk to half or
less; class ids nearest), boxes are shifted and scaled into its pixels and clipped to it. Area averaging keeps a fine
pattern from aliasing, but at a factor that is not a whole number OpenCV's costs about ten times bilinear's, on the one
thread that hands out every result, which then sets the pace of a GPU run (and on the submitting thread, a 1080p
camera's frame into a 720p canvas cost five times a bilinear resize); shrunk by less than half, bilinear still weighs in
every pixel. A frame of the canvas size passes through untouched and costs nothing here. So the same frame gives the
same outputs through every door, and a camera of another size gives outputs at its own size; setting input.height/width
to the camera's size spares the two host resizes.

A head's ``output.grid: native`` keeps its outputs in the canvas grid instead (``Result.grid`` says which, and
``Result.placement`` maps them). Which outputs are maps, class maps or boxes, a head says in ``meta["output_grid"]``
(``{"depth": "map", "classes": "labels", "boxes": "boxes"}``); for a head that does not, an output whose leading
two dimensions are the canvas's is a map (floating point) or a class map (integers), and a ``boxes`` output of
shape ``[N, 4]`` holds x1, y1, x2, y2 canvas pixels. Anything else passes unchanged.

Note [Empty boxes]
~~~~~~~~~~~~~~~~~~
A box that lies in the band around a frame, or reaches into it, is clipped to the frame's edge when mapped back;
what lay wholly in the band comes out with zero width or height (on a 300x1 frame nearly every box does). Such a
detection names no pixel of the frame, so :func:`drop_empty_boxes` drops it together with its row of every output
of the same length (scores, labels), and lowers ``count``. A fixed-capacity head keeps its shapes: the kept rows
move to the front, in their order, and the rows past the new count hold 0 (integers: -1), the detection heads'
padding. The same holds for boxes that are not mapped (a frame of the canvas's size, a head that keeps the canvas
grid with ``output.grid: native``) and for borrowed results: no result has a zero-area box.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from vpengine.config import EngineConfig
from vpengine.models.preprocess import IMAGENET_MEAN
from vpengine.specs import SpecDict

log = logging.getLogger("vpengine")

GridKind = Literal["map", "labels", "boxes"]
#: Gives the array of a shape and dtype that an output mapped to a frame's grid is written into.
Alloc = Callable[[tuple[int, ...], np.dtype], np.ndarray]
GRID_KINDS: tuple[str, ...] = ("map", "labels", "boxes")


@dataclass(frozen=True)
class Placement:
    """Where a frame of ``frame_hw`` lies in the canvas of ``canvas_hw``: the region ``x0, y0, w, h`` (Note [Frame
    grid]). The identity placement (frame == canvas) maps nothing."""

    frame_hw: tuple[int, int]
    canvas_hw: tuple[int, int]
    x0: int
    y0: int
    w: int
    h: int

    @classmethod
    def fit(cls, frame_hw: tuple[int, int], canvas_hw: tuple[int, int]) -> Placement:
        fh, fw = frame_hw
        ch, cw = canvas_hw
        if (fh, fw) == (ch, cw):
            return cls(frame_hw, canvas_hw, 0, 0, cw, ch)
        s = min(ch / fh, cw / fw)
        w = min(cw, max(1, round(fw * s)))
        h = min(ch, max(1, round(fh * s)))
        return cls(frame_hw, canvas_hw, (cw - w) // 2, (ch - h) // 2, w, h)

    @property
    def identity(self) -> bool:
        return self.frame_hw == self.canvas_hw

    def describe(self) -> str:
        fh, fw = self.frame_hw
        ch, cw = self.canvas_hw
        pad = f", {self.y0} px bands top and bottom" if self.y0 else ""
        pad += f", {self.x0} px bands left and right" if self.x0 else ""
        return f"{fw}x{fh} frames are scaled by {self.w / fw:.3g} into the {cw}x{ch} input{pad}"

    # ------------------------------------------------------------------------------------------- outputs
    def boxes_to_frame(self, boxes: Any) -> Any:
        """x1, y1, x2, y2 canvas pixels (numpy array or tensor, ``[..., 4]``) -> the frame's pixels, clipped to it."""
        fh, fw = self.frame_hw
        sx, sy = fw / self.w, fh / self.h
        if isinstance(boxes, torch.Tensor):
            off = torch.tensor([self.x0, self.y0, self.x0, self.y0], dtype=boxes.dtype, device=boxes.device)
            sc = torch.tensor([sx, sy, sx, sy], dtype=boxes.dtype, device=boxes.device)
            hi = torch.tensor([fw, fh, fw, fh], dtype=boxes.dtype, device=boxes.device)
            return torch.minimum(((boxes - off) * sc).clamp_min(0), hi)
        out = (boxes - np.array([self.x0, self.y0, self.x0, self.y0], boxes.dtype)) * np.array(
            [sx, sy, sx, sy], boxes.dtype
        )
        return np.minimum(np.maximum(out, 0), np.array([fw, fh, fw, fh], boxes.dtype)).astype(boxes.dtype)

    def to_frame(self, kind: GridKind, value: Any, alloc: Alloc | None = None) -> Any:
        """One output of ``kind`` in the canvas grid -> in the frame's (``value`` is left alone): a new array, or for
        a map one that ``alloc`` gives (see ``map_to_frame``)."""
        if kind == "boxes":
            return self.boxes_to_frame(value)
        return self.map_to_frame(value, labels=kind == "labels", alloc=alloc)

    @property
    def area_to_frame(self) -> bool:
        """Whether maps are area-averaged into the frame (else bilinear; Note [Frame grid])."""
        return _area_averaged((self.h, self.w), self.frame_hw)

    @property
    def area_to_canvas(self) -> bool:
        """Whether the frame is area-averaged into the canvas, by the same rule."""
        return _area_averaged(self.frame_hw, (self.h, self.w))

    def map_to_frame(self, m: Any, labels: bool, alloc: Alloc | None = None) -> Any:
        """A map ``[H, W, ...]`` in the canvas -> ``[h, w, ...]`` at the frame's size: the frame's region cut out
        and resized, values (``labels`` False) bilinear or area-averaged (Note [Frame grid]), class ids nearest.
        Numpy arrays or tensors. ``alloc(shape, dtype)``: where a 2-D numpy map OpenCV resizes is written (the
        engine's recycled result arrays), rather than new memory on every frame."""
        region = m[self.y0 : self.y0 + self.h, self.x0 : self.x0 + self.w]
        fh, fw = self.frame_hw
        if isinstance(m, torch.Tensor):
            return _resize_tensor(region, (fh, fw), labels, shrink=self.area_to_frame)
        import cv2

        def resized(interpolation: int) -> np.ndarray:
            dst = alloc((fh, fw), region.dtype) if alloc is not None and region.ndim == 2 else None
            return cv2.resize(region, (fw, fh), dst=dst, interpolation=interpolation)

        if labels:
            if region.dtype in _CV_NEAREST:
                return resized(cv2.INTER_NEAREST_EXACT)
            rows = np.minimum(((np.arange(fh) + 0.5) * (self.h / fh)).astype(np.intp), self.h - 1)
            cols = np.minimum(((np.arange(fw) + 0.5) * (self.w / fw)).astype(np.intp), self.w - 1)
            return region[rows][:, cols]
        filt = cv2.INTER_AREA if self.area_to_frame else cv2.INTER_LINEAR
        if region.dtype in _CV_LINEAR:
            return resized(filt)
        return cv2.resize(region.astype(np.float32), (fw, fh), interpolation=filt).astype(m.dtype)


# what cv2.resize takes for each filter (int32/int64 class maps are indexed by hand)
SIZES_KEPT = 8  # buffers kept per frame size (by last use): enough for every camera of a robot, bounded for a folder


def buffer_for(cache: dict[tuple[int, int], np.ndarray], size: tuple[int, int], dtype: Any) -> np.ndarray:
    """A ``size`` HxWx3 buffer from ``cache``, made on first use: one per frame size, not one per frame, and at most
    SIZES_KEPT sizes (the least recently used goes), so a stream of ever new sizes does not grow memory."""
    buf = cache.pop(size, None)
    if buf is None:
        buf = np.zeros((*size, 3), dtype)
        while len(cache) >= SIZES_KEPT:
            del cache[next(iter(cache))]
    cache[size] = buf  # last used goes last
    return buf


#: Maps shrunk by this factor or more are area-averaged, by less bilinear (Note [Frame grid]).
AREA_SHRINK = 2


def _area_averaged(src_hw: tuple[int, int], dst_hw: tuple[int, int]) -> bool:
    """Whether resizing ``src_hw`` to ``dst_hw`` shrinks by AREA_SHRINK or more on both axes."""
    return min(s / d for s, d in zip(src_hw, dst_hw)) >= AREA_SHRINK


_CV_NEAREST = {np.dtype(t) for t in ("uint8", "int8", "uint16", "int16", "float32", "float64")}
_CV_LINEAR = {np.dtype(t) for t in ("uint8", "uint16", "int16", "float32", "float64")}


def _resize_tensor(region: torch.Tensor, size: tuple[int, int], labels: bool, shrink: bool) -> torch.Tensor:
    extra = region.shape[2:]
    x = region.reshape(*region.shape[:2], -1).permute(2, 0, 1)[None]  # 1, C, h, w
    if labels:  # exact for class ids below 2**24
        y = torch.nn.functional.interpolate(x.float(), size=size, mode="nearest-exact")
    else:
        y = torch.nn.functional.interpolate(
            x.float(), size=size, mode="bilinear", align_corners=False, antialias=shrink
        )
        if not region.dtype.is_floating_point:
            y = y.round()
    return y[0].permute(1, 2, 0).reshape(*size, *extra).to(region.dtype)


def drop_empty_boxes(outputs: dict[str, Any], kinds: dict[str, GridKind]) -> dict[str, Any]:
    """``outputs`` (mapped to a frame) without the detections whose box has zero width or height (Note [Empty
    boxes]); unchanged when none has or the head has no one ``[M, 4]`` boxes output. Numpy arrays or tensors. A
    fixed-capacity head (one with a ``count``) keeps its shapes, and its tensors stay on their device without a
    sync; without a count the rows kept are picked by a boolean mask, which waits for the device."""
    keys = [k for k, kind in kinds.items() if kind == "boxes" and k in outputs]
    if len(keys) != 1:
        return outputs
    boxes = outputs[keys[0]]
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        return outputs
    m = boxes.shape[0]
    rows = [k for k, v in outputs.items() if k != "count" and kinds.get(k) in (None, "boxes") and _rows(v) == m]
    count = outputs.get("count")
    keep = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
    if isinstance(boxes, torch.Tensor):
        if count is not None:
            keep &= torch.arange(m, device=boxes.device) < torch.as_tensor(count, device=boxes.device)
            order = torch.argsort((~keep).to(torch.uint8), stable=True)
            n = keep.sum()
            tail = torch.arange(m, device=boxes.device) >= n
            out = {**outputs, "count": n.to(count.dtype).reshape(count.shape) if torch.is_tensor(count) else n}
            for k in rows:
                v = outputs[k][order]
                pad = -1 if not v.dtype.is_floating_point and v.dtype != torch.bool and v.dtype.is_signed else 0
                out[k] = v.masked_fill(tail.reshape(-1, *([1] * (v.ndim - 1))), pad)
            return out
        return {**outputs, **{k: outputs[k][keep] for k in rows}}
    keep = np.asarray(keep)
    if count is not None:
        n_in = int(np.asarray(count))
        if keep[:n_in].all():
            return outputs
        keep[n_in:] = False
        n = int(keep.sum())
        order = np.argsort(~keep, kind="stable")
        out = {**outputs, "count": np.asarray(n, np.asarray(count).dtype).reshape(np.shape(count))}
        for k in rows:
            v = np.asarray(outputs[k])[order]
            v[n:] = -1 if v.dtype.kind == "i" else 0
            out[k] = v
        return out
    if keep.all():
        return outputs
    return {**outputs, **{k: np.asarray(outputs[k])[keep] for k in rows}}


def _rows(v: Any) -> int | None:
    shape = getattr(v, "shape", ())
    return shape[0] if len(shape) else None


def output_kinds(meta: dict[str, Any], spec: SpecDict, canvas_hw: tuple[int, int]) -> dict[str, GridKind]:
    """Which of a head's outputs are maps, class maps or boxes in the canvas grid (Note [Frame grid])."""
    declared = dict(meta.get("output_grid") or {})
    bad = {k: v for k, v in declared.items() if v not in GRID_KINDS or k not in spec}
    if bad:
        raise ValueError(
            f"meta['output_grid'] {bad}: each key must be an output ({', '.join(spec) or 'none'}) and each kind one of "
            f"{GRID_KINDS}"
        )
    kinds: dict[str, GridKind] = {}
    for k, s in spec.items():
        if k in declared:
            kinds[k] = declared[k]
        elif s.shape[:2] == canvas_hw:
            kinds[k] = "map" if s.torch_dtype.is_floating_point else "labels"
        elif k == "boxes" and len(s.shape) == 2 and s.shape[1] == 4:
            kinds[k] = "boxes"
    return kinds


def _output_kinds(head: str, meta: dict[str, Any], spec: SpecDict, canvas_hw: tuple[int, int]) -> dict[str, GridKind]:
    """``output_kinds`` of head ``head``, its name in the error."""
    try:
        return output_kinds(meta, spec, canvas_hw)
    except ValueError as e:
        raise ValueError(f"head {head!r}: {e}") from None


class Boundary:
    """Frames in (checked, fitted into the input canvas); outputs go back through :meth:`to_frame` (each frame's
    ``Placement`` with the kinds in ``kinds``). One per engine, whatever the cameras (each frame carries its own
    placement); ``write`` runs in the submitting threads, several cameras' at once (Note [Frames of several cameras
    at once] in core.py): it writes only into the slot it is given."""

    def __init__(
        self,
        cfg: EngineConfig,
        heads: dict[str, tuple[dict[str, Any], SpecDict]],
        normalize_mean: tuple[float, ...] = IMAGENET_MEAN,
    ) -> None:
        inp = cfg.input
        self.canvas_hw = (inp.height, inp.width)
        self.dtype = np.dtype(inp.dtype)
        self.color = inp.color
        self.max_side = inp.max_frame_side
        mean = np.asarray(normalize_mean, np.float64)
        if inp.color == "bgr":
            mean = mean[::-1]
        # the padding is the normalisation mean: zero once normalised
        self.pad = (mean * 255).round().astype(self.dtype) if self.dtype == np.uint8 else mean.astype(self.dtype)
        self.kinds = {h: _output_kinds(h, meta, spec, self.canvas_hw) for h, (meta, spec) in heads.items()}
        self.native = {h.name for h in cfg.heads if h.output.grid == "native"}
        self._placements: dict[tuple[int, int], Placement] = {}
        self._pad_row = np.tile(self.pad, (self.canvas_hw[1], 1))  # one canvas row of pad pixels

    def add_head(self, name: str, meta: dict[str, Any], spec: SpecDict, native: bool) -> None:
        """A head added at run time: how its outputs map to a frame's grid (``native``: output.grid native)."""
        self.kinds = {**self.kinds, name: _output_kinds(name, meta, spec, self.canvas_hw)}
        self.native = self.native | {name} if native else self.native - {name}

    def remove_head(self, name: str) -> None:
        self.kinds = {h: k for h, k in self.kinds.items() if h != name}
        self.native = self.native - {name}

    def describe_expected(self) -> str:
        h, w = self.canvas_hw
        return (
            f"an HxWx3 {self.dtype} numpy array ({self.color.upper()}) of any size up to {self.max_side} px a side "
            f"(the models run at {w}x{h})"
        )

    def check(self, frame: Any) -> np.ndarray:
        """The frame as a numpy array, or ValueError naming what was expected and what came."""
        want = self.describe_expected()
        if isinstance(frame, torch.Tensor):
            if frame.device.type != "cpu":
                raise ValueError(f"expected {want}; got a tensor on {frame.device} (submit host frames)")
            if frame.requires_grad:
                raise ValueError(f"expected {want}; got a tensor that requires grad (submit frame.detach())")
            frame = frame.numpy()
        if not isinstance(frame, np.ndarray):
            raise ValueError(f"expected {want}; got {type(frame).__name__}")
        if frame.size == 0:
            raise ValueError(f"expected {want}; got an empty array of shape {frame.shape}")
        if frame.ndim != 3 or frame.shape[2] != 3:
            if frame.ndim == 2 or (frame.ndim == 3 and frame.shape[2] == 1):
                why = "a single-channel image: convert it, e.g. cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)"
            elif frame.ndim == 3:
                why = f"{frame.shape[2]} channels"
            else:
                why = f"{frame.ndim} dimensions"
            raise ValueError(f"expected {want}; got shape {frame.shape} ({why})")
        if max(frame.shape[:2]) > self.max_side:
            raise ValueError(
                f"expected {want}; got {frame.shape[1]}x{frame.shape[0]} (raise input.max_frame_side to allow it)"
            )
        if frame.dtype != self.dtype:
            raise ValueError(f"expected {want}; got dtype {frame.dtype}")
        if frame.dtype.kind == "f":
            hi = float(frame.max())  # NaN if any is (and inf if any is): no mask made
            if not np.isfinite(hi) or not np.isfinite(float(frame.min())):
                raise ValueError(f"expected {want} with finite values; got NaN or inf")
            if hi > 2.0:  # a float frame is 0..1: this one is 0..255, its /255 forgotten
                raise ValueError(f"expected {want} with values 0..1; got values up to {hi:g} (divide by 255)")
        return frame

    def picture(self, frame: np.ndarray) -> np.ndarray:
        """A checked frame as the BGR uint8 picture ``Result.plot`` draws on (frames may be RGB, or float32
        0..1)."""
        pic = frame
        if pic.dtype != np.uint8:
            pic = (np.clip(pic, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        return np.ascontiguousarray(pic[..., ::-1]) if self.color == "rgb" else pic

    def placement(self, frame_hw: tuple[int, int]) -> Placement:
        p = self._placements.get(frame_hw)
        if p is None:  # two cameras' threads may get here at once: one placement kept, logged once
            fresh = Placement.fit(frame_hw, self.canvas_hw)
            p = self._placements.setdefault(frame_hw, fresh)
            if p is fresh and not p.identity:
                log.info("%s; set input.height/width to that size to spare the resizing", p.describe())
        return p

    def to_frame(self, head: str, outputs: dict[str, Any], placement: Placement | None) -> dict[str, Any]:
        """``head``'s ``outputs`` (host arrays or tensors) in the grid of the frame at ``placement``: as they are,
        unless the head keeps the canvas grid (``output.grid: native``), whose maps and boxes are then mapped the way
        the engine maps every other head's (Note [Frame grid]). For whoever draws a result on its frame."""
        if head not in self.native or placement is None or placement.identity:
            return outputs
        kinds = self.kinds[head]
        return {k: placement.to_frame(kinds[k], v) if k in kinds else v for k, v in outputs.items()}

    def write(self, frame: np.ndarray, dst: np.ndarray) -> Placement:
        """Fit a checked ``frame`` into the canvas ``dst`` (an input slot); returns where it went."""
        p = self.placement(frame.shape[:2])
        if p.identity:
            # numpy, not torch: torch parallelises host copies over its OpenMP pool, whose idle threads then spin
            # (one per core); a plain memcpy costs a fraction of that at 30 Hz.
            np.copyto(dst, frame)
            return p
        import cv2

        # resized straight into the slot's region (OpenCV writes into a strided view of the right size and type),
        # and the bands filled from rows of pad pixels: broadcasting the 3-channel pad pixel itself makes numpy
        # copy 3 bytes at a time, an order of magnitude slower than copying whole rows
        y0, x0, y1, x1 = p.y0, p.x0, p.y0 + p.h, p.x0 + p.w
        region = dst[y0:y1, x0:x1]
        out = cv2.resize(
            np.ascontiguousarray(frame),
            (p.w, p.h),
            dst=region,
            interpolation=cv2.INTER_AREA if p.area_to_canvas else cv2.INTER_LINEAR,
        )
        if out is not region:  # pragma: no cover - an OpenCV that would not write into the view
            region[...] = out
        row = self._pad_row
        dst[:y0] = row
        dst[y1:] = row
        dst[y0:y1, :x0] = row[:x0]
        dst[y0:y1, x1:] = row[x1:]
        return p
