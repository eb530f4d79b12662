"""Sinks: where results go. A folder of files per head, annotated pictures or an annotated video, or a callback.

Folder layout (``vpengine run --out DIR``; with several cameras each camera's head folders are in ``DIR/<camera>/``
instead, and the summary covers them all)::

    DIR/summary.json            achieved rates, skipped/dropped frames, latency percentiles per model, results
                                left unwritten (Note [Sink thread]), camera frames replaced (Note [Live capture]),
                                inputs skipped as unreadable or decoded partially (images, videos that end short)
    DIR/<head>/<frame>.png      depth as 16-bit PNG (``depth_format="png16"``, the default; Note [Depth PNG]), with
    DIR/<head>/depth_scale.jsonl  one line per PNG: the offset and scale that give the depth back
    DIR/<head>/<frame>.npy      depth as float32 (``depth_format="npy"``: exact, about 12x the PNG's size)
    DIR/<head>/<frame>.png      segmentation class ids (uint8, uint16 beyond 256 classes)
    DIR/<head>/detections.jsonl one line per frame: every detection with box, score, label and name
    DIR/<head>/<frame>.npz      any other head: all its output arrays
    DIR/<head>/viz/...          pictures (with --viz): depth with a colour bar, overlays, boxes
"""

from __future__ import annotations

import collections
import json
import math
import os
import queue
import threading
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import numpy as np

from vpengine import visualize
from vpengine.engine.results import Result
from vpengine.io.video import VideoWriter, check_name, even_size

DEPTH_FORMATS = ("png16", "npy")
#: Pictures are JPEGs of this quality: a third of quality 95's size (OpenCV's default), no difference to the eye.
JPEG_QUALITY = 90
#: Threads that write a folder sink's files (Note [Parallel file writes]).
FILE_WRITERS = min(8, os.cpu_count() or 1)


class Sink:
    def write(self, result: Result, frame: np.ndarray | None, name: str) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def close(self) -> None:
        pass


class SinkThread:
    """Note [Sink thread]: writes results to sinks on one background thread, in the order they were put.

    Files and pictures take longer than a frame on a small computer (a colour-mapped depth PNG and two JPEG
    overlays of a 768x576 frame: about 14 ms on a 2-core CPU), and written in the frame loop they held up every
    next frame by that much. Here the loop only queues a result (a copy, so nothing the engine reuses) and goes
    on, and the engine's models and the writing overlap. ``block=True`` (lockstep: nothing may be lost) waits while
    ``max_pending`` results are queued; ``block=False`` (a live source must not fall behind) leaves such a result
    unwritten and counts it per head in ``unwritten``.

    The sinks are made, written and closed on the writer thread alone (an SQLite bag may be used only by the
    thread that opened it); making them is waited for, and an error there is raised from the constructor as it
    is. A sink that raises while writing stops the writing: the next ``put`` or ``close`` raises it, and results
    queued after it are discarded, so neither ever waits on a dead writer. ``close`` writes what is queued, then
    closes every sink, then reports the first error."""

    def __init__(self, factories: Sequence[Callable[[], Sink]], max_pending: int, block: bool) -> None:
        if max_pending < 1:
            raise ValueError(f"max_pending must be >= 1, got {max_pending}")
        self._block = block
        self._q: queue.Queue[tuple[Result, np.ndarray | None, str] | None] = queue.Queue(max_pending)
        self._error: BaseException | None = None
        self._close_error: BaseException | None = None
        self._reported = False  # raised once already: close does not raise it again
        self._closed = False
        self.unwritten: collections.Counter[str] = collections.Counter()
        ready = threading.Event()
        self._thread = threading.Thread(
            target=self._run, args=(list(factories), ready), name="vpengine-sinks", daemon=True
        )
        self._thread.start()
        ready.wait()
        if self._error is not None:  # a sink could not be made (nothing was put yet: no write failed)
            self._thread.join()
            self._closed = True
            raise self._error

    def put(self, result: Result, frame: np.ndarray | None, name: str) -> bool:
        """Queue a result for the sinks; False when it is left unwritten (``block=False`` and the queue full)."""
        self.check()
        item = (result, frame, name)
        if not self._block:
            try:
                self._q.put_nowait(item)
            except queue.Full:
                self.unwritten[result.head] += 1
                return False
            return True
        while True:
            try:
                self._q.put(item, timeout=0.5)
                return True
            except queue.Full:
                self.check()

    def check(self) -> None:
        """Raise the error a sink raised while writing, if one did."""
        if self._error is not None:
            self._reported = True
            raise RuntimeError(f"writing outputs failed: {self._error!r}") from self._error

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._q.put(None)  # the thread always drains (it discards after an error), so this never waits long
        self._thread.join()
        if not self._reported:
            self.check()
        if self._close_error is not None:
            raise RuntimeError(f"closing outputs failed: {self._close_error!r}") from self._close_error

    def _run(self, factories: list[Callable[[], Sink]], ready: threading.Event) -> None:
        sinks: list[Sink] = []
        try:
            for make in factories:
                sinks.append(make())
        except BaseException as e:
            self._error = e
            self._close(sinks)
            return
        finally:
            ready.set()
        while (item := self._q.get()) is not None:
            if self._error is not None:
                continue
            try:
                for sink in sinks:
                    sink.write(*item)
            except BaseException as e:
                self._error = e
        self._close(sinks)

    def _close(self, sinks: list[Sink]) -> None:
        for sink in sinks:  # every one, whatever the others do
            try:
                sink.close()
            except Exception as e:
                self._close_error = self._close_error or e


class CameraSinks(Sink):
    """Each result to the sink of its camera (``Result.camera``): with several cameras every camera's outputs have
    a sink of their own (``DIR/<camera>/<head>/...``, one video per camera). Results of a camera without a sink are
    dropped. ``close`` closes every sink, then raises the first error."""

    def __init__(self, sinks: Mapping[str, Sink]) -> None:
        self.sinks = dict(sinks)

    def write(self, result: Result, frame: np.ndarray | None, name: str) -> None:
        sink = self.sinks.get(result.camera)
        if sink is not None:
            sink.write(result, frame, name)

    def close(self) -> None:
        error: Exception | None = None
        for sink in self.sinks.values():
            try:
                sink.close()
            except Exception as e:
                error = error or e
        if error is not None:
            raise error


def per_camera(
    served: Mapping[str, Sequence[str]],
    heads: Mapping[str, dict[str, Any]],
    make: Callable[[str | None, dict[str, dict[str, Any]]], Sink],
) -> Sink:
    """``make(camera, heads)`` for each camera (``served``: camera -> the heads that serve it) under a
    :class:`CameraSinks`; with one camera the one sink ``make(None, heads)``, laid out as always."""
    if len(served) <= 1:
        return make(None, dict(heads))
    return CameraSinks({c: make(c, {h: heads[h] for h in hs}) for c, hs in served.items()})


def encode_depth_png(depth: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Note [Depth PNG]: a float depth map as a 16-bit image plus the two numbers that give it back.

    The finite values' range is spread over 1..65535 (``value = offset + (pixel - 1) * scale``) and 0 marks a pixel
    that was NaN or infinite, so the error is at most half a step: 1/131070 of the frame's range, far below what
    any depth model resolves, for half of float32's size before compression. Written with PNG's Sub filter alone
    (each pixel less its left neighbour; :func:`_png16_params`), where libpng's default tries five filters per
    row: on the tiny models' depth of the street video 2.5x smaller and twice as fast (144 KB and 6 ms against
    368 KB and 14 ms a 768x576 frame; smooth maps suit it, as depth maps are). Returns (uint16 map, offset,
    scale); :func:`decode_depth_png` inverts it."""
    d = np.asarray(depth, dtype=np.float32)
    finite = np.isfinite(d)
    all_finite = bool(finite.all())
    if not all_finite and not finite.any():
        return np.zeros(d.shape, np.uint16), 0.0, 0.0
    valid = d if all_finite else d[finite]
    lo, hi = float(valid.min()), float(valid.max())
    scale = (hi - lo) / 65534 if hi > lo else 0.0
    # float32 is exact enough here (6e-8 * 65534 = 0.004 of a step) and 4x faster than float64 at 1080p
    q = np.subtract(d, np.float32(lo), dtype=np.float32)
    q *= np.float32(1 / scale if scale else 0.0)
    q += 1
    np.rint(q, out=q)
    if not all_finite:
        q[~finite] = 0
    return np.clip(q, 0, 65535, out=q).astype(np.uint16), lo, scale


def decode_depth_png(png: np.ndarray, offset: float, scale: float) -> np.ndarray:
    """The float32 depth of a 16-bit depth PNG (Note [Depth PNG]); NaN where it was not finite."""
    q = np.asarray(png)
    d = (offset + (q.astype(np.float64) - 1) * scale).astype(np.float32)
    d[q == 0] = np.nan
    return d


def load_depth(head_dir: str | Path, frame: str | int) -> np.ndarray:
    """Depth of ``frame`` as written by :class:`FolderSink` to ``head_dir``: the ``.npy`` file, or the 16-bit PNG
    decoded with its line of ``depth_scale.jsonl``. ``frame``: the file's name without its suffix (an image's own
    name, a video's frame as ``000042``), or a video frame's number (42)."""
    import cv2

    if isinstance(frame, (int, np.integer)) and not isinstance(frame, bool):
        frame = f"{int(frame):06d}"
    d = Path(head_dir)
    if (d / f"{frame}.npy").is_file():
        return np.load(d / f"{frame}.npy")
    with open(d / "depth_scale.jsonl") as f:
        lines = [json.loads(line) for line in f]
    rec = next((r for r in reversed(lines) if r["frame"] == frame), None)
    if rec is None:
        some = ", ".join(repr(r["frame"]) for r in lines[:3])
        raise KeyError(
            f"no depth of frame {frame!r} in {str(d / 'depth_scale.jsonl')!r} ({len(lines)} frames: {some}"
            f"{' ...' if len(lines) > 3 else ''})"
        )
    png = cv2.imread(str(d / f"{frame}.png"), cv2.IMREAD_UNCHANGED)
    if png is None:
        raise FileNotFoundError(f"cannot read depth image {str(d / f'{frame}.png')!r}")
    return decode_depth_png(png, rec["offset"], rec["scale"])


class FolderSink(Sink):
    """Every head's outputs as files in ``out_dir`` (layout in the module's docstring). Line files
    (``detections.jsonl``, ``depth_scale.jsonl``) are started afresh, never appended to. Pictures and arrays are
    written on threads of their own (Note [Parallel file writes]): every file is there once ``close`` returns."""

    def __init__(
        self,
        out_dir: str | Path,
        heads: dict[str, dict[str, Any]],
        viz: bool = False,
        save_every: int = 1,
        depth_format: str = "png16",
    ) -> None:
        if save_every < 1:
            raise ValueError(f"save_every must be >= 1, got {save_every}")
        if depth_format not in DEPTH_FORMATS:
            raise ValueError(f"depth_format must be one of {DEPTH_FORMATS}, got {depth_format!r}")
        self.dir = Path(out_dir)
        self.heads = heads
        self.viz = viz
        self.save_every = save_every
        self.depth_format = depth_format
        self._count: dict[str, int] = dict.fromkeys(heads, 0)
        self._jsonl: dict[tuple[str, str], Any] = {}
        for h in heads:
            (self.dir / h).mkdir(parents=True, exist_ok=True)
            if viz:
                (self.dir / h / "viz").mkdir(exist_ok=True)
        self.written: dict[str, int] = dict.fromkeys(heads, 0)
        self._files = _FileWrites(FILE_WRITERS)

    def _line(self, head: str, file: str, record: dict[str, Any]) -> None:
        f = self._jsonl.get((head, file))
        if f is None:
            f = self._jsonl[(head, file)] = open(self.dir / head / file, "w")  # noqa: SIM115
        f.write(json.dumps(record) + "\n")

    def write(self, result: Result, frame: np.ndarray | None, name: str) -> None:
        h = result.head
        info = self.heads[h]
        kind = visualize.head_kind(info)
        out = result.outputs
        if kind == "detection":  # one small line per frame: always written, whatever save_every says
            names = info.get("labels")
            boxes, scores, labels = visualize.detections(out)
            label_list = labels.tolist()
            self._line(
                h,
                "detections.jsonl",
                {
                    "frame": name,
                    "frame_id": result.frame_id,
                    "capture_time": result.capture_time,
                    "boxes": boxes.round(2).tolist(),
                    "scores": scores.round(4).tolist(),
                    "labels": label_list,
                    "names": [names[i] if names and 0 <= i < len(names) else str(i) for i in label_list],
                },
            )
        self._count[h] += 1
        if (self._count[h] - 1) % self.save_every:
            return
        d = self.dir / h
        files = self._files
        if kind == "depth":
            if "depth" in out and self.depth_format == "npy":
                files.submit(np.save, d / f"{name}.npy", np.asarray(out["depth"], dtype=np.float32))
            elif "depth" in out:
                png, offset, scale = encode_depth_png(visualize.plane(out["depth"], _map_size(result)))
                files.submit(_imwrite, d / f"{name}.png", png, _png16_params())
                self._line(
                    h,
                    "depth_scale.jsonl",
                    {"frame": name, "frame_id": result.frame_id, "offset": offset, "scale": scale},
                )
            if "depth_color" in out:  # the head colour-mapped it already (postprocess output: colormap|both)
                files.submit(_imwrite, d / f"{name}_color.png", np.asarray(out["depth_color"]))
        elif kind == "segmentation":
            cls = np.asarray(out["classes"])
            files.submit(_imwrite, d / f"{name}.png", cls.astype(np.uint8 if cls.max(initial=0) < 256 else np.uint16))
        elif kind != "detection":
            files.submit(np.savez, d / f"{name}.npz", **{k: np.asarray(v) for k, v in out.items()})
        self.written[h] += 1
        if self.viz and (frame is not None or kind == "depth"):
            files.submit(_draw_jpeg, d / "viz" / f"{name}.jpg", frame, out, info, h)

    def close(self) -> None:
        try:
            self._files.close()
        finally:
            for f in self._jsonl.values():
                f.close()
            self._jsonl.clear()


class _FileWrites:
    """Note [Parallel file writes]: encoding a frame's pictures takes longer than a frame at the rates a GPU
    runs (a 16-bit depth PNG and a colour-mapped one take several frame periods of a 150 Hz run on one core),
    and on the one sink thread (Note [Sink thread]) a lockstep run waited for them. So every file is written by a small pool of threads (OpenCV and numpy let go of the GIL
    while they encode), while the sink thread goes on with the next result; what has to be in order (the lines
    of ``detections.jsonl`` and ``depth_scale.jsonl``) stays on the sink thread. At most ``2 * workers`` files are
    in the works: one more waits for the oldest. A write that failed raises its error (naming the file) from a
    later ``submit`` or from ``close``, which first waits for every write in the works, so no file is lost
    unnoticed. What a write is given is not touched again here: a result's arrays are its own (Note [Borrowed
    results] in engine/results.py) and stay alive while the write refers to them."""

    def __init__(self, workers: int) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="vpengine-files")
        self._pending: collections.deque[Future[Any]] = collections.deque()
        self._most = 2 * workers

    def submit(self, write: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        while self._pending and (self._pending[0].done() or len(self._pending) >= self._most):
            self._pending.popleft().result()  # raises a failed write's error
        self._pending.append(self._pool.submit(write, *args, **kwargs))

    def close(self) -> None:
        try:
            while self._pending:
                self._pending.popleft().result()
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)


class AnnotatedSink(Sink):
    """Note [Annotated frames]: one picture per frame of the input and every head side by side
    (:func:`visualize.draw_results`), written as ``<pictures>/<frame>.jpg`` and/or as the frames of a ``video`` (H.264
    in mp4 where an encoder is there: Note [Browser video] in io/video.py).

    Results arrive one head at a time; a frame is drawn once every head has answered it, or once ``lag`` newer
    frames are waiting (a head limited to a lower rate, paused, or slower, never answers some frames). A head
    that did not answer a frame is shown with its newest earlier result, as a live view would; one that has never
    answered as 'no result yet'. Video frames all have the first picture's size (rounded up to even numbers): a
    picture of another size (a folder of mixed sizes) is scaled into it with its aspect kept, never stretched."""

    def __init__(
        self,
        heads: Mapping[str, Mapping[str, Any]],
        pictures: str | Path | None = None,
        video: str | Path | None = None,
        fps: float = 30.0,
        lag: int = 2,
    ) -> None:
        if pictures is None and video is None:
            raise ValueError("AnnotatedSink needs a pictures folder, a video file or both")
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"video rate must be a number of Hz above 0, got {fps}")
        self.heads = dict(heads)
        self.pictures = None if pictures is None else Path(pictures)
        self.video = None if video is None else check_name(video)  # refused now, not at the first frame
        self.fps = fps
        self.lag = lag
        self.frames_written = 0
        self._pending: collections.OrderedDict[int, tuple[np.ndarray, str, dict[str, Any]]] = collections.OrderedDict()
        self._newest: dict[str, Any] = {}
        self._writer: VideoWriter | None = None
        self._size: tuple[int, int] | None = None
        if self.pictures is not None:
            self.pictures.mkdir(parents=True, exist_ok=True)

    def write(self, result: Result, frame: np.ndarray | None, name: str) -> None:
        if frame is None or result.head not in self.heads:  # nothing to draw on
            return
        _, _, got = self._pending.setdefault(result.frame_id, (frame, name, {}))
        got[result.head] = result.outputs
        if len(got) == len(self.heads):
            while self._pending:  # older frames first, so the video stays in order
                fid = next(iter(self._pending))
                self._draw(fid)
                if fid == result.frame_id:
                    break
        while len(self._pending) > self.lag:
            self._draw(next(iter(self._pending)))

    def _draw(self, frame_id: int) -> None:
        frame, name, got = self._pending.pop(frame_id)
        self._newest.update(got)
        picture = visualize.draw_results(frame, {h: got.get(h, self._newest.get(h)) for h in self.heads}, self.heads)
        if self.pictures is not None:
            _write_jpeg(self.pictures / f"{name}.jpg", picture)
        if self.video is not None:
            if self._writer is None:
                self._size = even_size(picture.shape[1], picture.shape[0])
                self._writer = VideoWriter(self.video, self.fps, self._size)
            self._writer.write(_fit(picture, self._size or (0, 0)))
        self.frames_written += 1

    def close(self) -> None:
        try:
            while self._pending:
                self._draw(next(iter(self._pending)))
        finally:
            if self._writer is not None:
                self._writer.close()
                self._writer = None


def _map_size(result: Result) -> tuple[int, int] | None:
    """The (height, width) of ``result``'s maps: its frame's, or the models' input canvas for a native-grid head."""
    if result.grid == "native" and result.placement is not None:
        return result.placement.canvas_hw
    return result.frame_size if all(result.frame_size) else None


def _imwrite(path: Path, image: np.ndarray, params: Sequence[int] = ()) -> None:
    """cv2.imwrite that raises instead of returning False (a full disk must not lose outputs unnoticed)."""
    import cv2

    if not cv2.imwrite(str(path), image, list(params)):
        raise OSError(f"cannot write {str(path)!r}")


def _png16_params() -> list[int]:
    """PNG options for depth (Note [Depth PNG]): fast deflate, the Sub filter where OpenCV can choose it (4.10+)."""
    import cv2

    params = [cv2.IMWRITE_PNG_COMPRESSION, 1]
    if hasattr(cv2, "IMWRITE_PNG_FILTER"):
        params += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_SUB]
    return params


def _draw_jpeg(path: Path, frame: np.ndarray | None, outputs: dict[str, Any], info: dict[str, Any], head: str) -> None:
    _write_jpeg(path, visualize.draw_result(frame, outputs, info, head))


def _write_jpeg(path: Path, picture: np.ndarray) -> None:
    import cv2

    _imwrite(path, picture, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])


def _fit(picture: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``picture`` scaled into ``size`` (width, height) with its aspect kept, on black."""
    import cv2

    w, h = size
    ph, pw = picture.shape[:2]
    if (pw, ph) == (w, h):
        return picture
    s = min(w / pw, h / ph)
    nw, nh = max(1, round(pw * s)), max(1, round(ph * s))
    out = np.zeros((h, w, 3), np.uint8)
    y, x = (h - nh) // 2, (w - nw) // 2
    out[y : y + nh, x : x + nw] = cv2.resize(picture, (nw, nh), interpolation=cv2.INTER_AREA)
    return out
