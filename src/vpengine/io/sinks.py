"""Sinks: where results go. A folder of files per head, or a callback.

Folder layout (``vpengine run --out DIR``)::

    DIR/summary.json            achieved rates, skipped/dropped frames, latency percentiles per model, results
                                left unwritten (Note [Sink thread]), camera frames replaced (Note [Live capture])
    DIR/<head>/<frame>.npy      depth, float32 at input resolution (never quantised)
    DIR/<head>/<frame>.png      segmentation class ids (uint8, uint16 beyond 256 classes)
    DIR/<head>/detections.jsonl one line per frame: every detection with box, score, label and name
    DIR/<head>/<frame>.npz      any other head: all its output arrays
    DIR/<head>/viz/...          pictures (with --viz): colour-mapped depth, overlays, boxes
"""

from __future__ import annotations

import collections
import json
import queue
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from vpengine.engine import Result
from vpengine.io import visualize


class Sink:
    def write(
        self, result: Result, frame: np.ndarray | None, name: str
    ) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def close(self) -> None:
        pass


class CallbackSink(Sink):
    def __init__(self, fn: Callable[[Result, np.ndarray | None], None]) -> None:
        self.fn = fn

    def write(self, result: Result, frame: np.ndarray | None, name: str) -> None:
        self.fn(result, frame)


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

    def put(self, result: Result, frame: np.ndarray | None, name: str) -> None:
        self.check()
        item = (result, frame, name)
        if not self._block:
            try:
                self._q.put_nowait(item)
            except queue.Full:
                self.unwritten[result.head] += 1
            return
        while True:
            try:
                self._q.put(item, timeout=0.5)
                return
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


def head_kind(info: dict[str, Any]) -> str:
    """What a head produces, from its metadata (``kind``) or its output names."""
    if info.get("kind"):
        return str(info["kind"])
    outs = set(info.get("outputs", {}))
    if "depth" in outs:
        return "depth"
    if "classes" in outs:
        return "segmentation"
    if {"boxes", "scores", "labels"} <= outs:
        return "detection"
    return "generic"


class FolderSink(Sink):
    def __init__(
        self, out_dir: str | Path, heads: dict[str, dict[str, Any]], viz: bool = False, save_every: int = 1
    ) -> None:
        if save_every < 1:
            raise ValueError(f"save_every must be >= 1, got {save_every}")
        self.dir = Path(out_dir)
        self.heads = heads
        self.viz = viz
        self.save_every = save_every
        self._count: dict[str, int] = dict.fromkeys(heads, 0)
        self._jsonl: dict[str, Any] = {}
        for h in heads:
            (self.dir / h).mkdir(parents=True, exist_ok=True)
            if viz:
                (self.dir / h / "viz").mkdir(exist_ok=True)
        self.written: dict[str, int] = dict.fromkeys(heads, 0)

    def write(self, result: Result, frame: np.ndarray | None, name: str) -> None:
        h = result.head
        info = self.heads[h]
        kind = head_kind(info)
        out = result.outputs
        if kind == "detection":  # one small line per frame: always written, whatever save_every says
            f = self._jsonl.get(h)
            if f is None:
                f = self._jsonl[h] = open(self.dir / h / "detections.jsonl", "a")  # noqa: SIM115
            names = info.get("labels")
            labels = np.asarray(out["labels"]).tolist()
            f.write(
                json.dumps(
                    {
                        "frame": name,
                        "frame_id": result.frame_id,
                        "capture_time": result.capture_time,
                        "boxes": np.asarray(out["boxes"]).round(2).tolist(),
                        "scores": np.asarray(out["scores"]).round(4).tolist(),
                        "labels": labels,
                        "names": [names[i] if names and 0 <= i < len(names) else str(i) for i in labels],
                    }
                )
                + "\n"
            )
        self._count[h] += 1
        if (self._count[h] - 1) % self.save_every:
            return
        d = self.dir / h
        if kind == "depth":
            if "depth" in out:
                np.save(d / f"{name}.npy", np.asarray(out["depth"], dtype=np.float32))
            if "depth_color" in out:  # the head colour-mapped it already (postprocess output: colormap|both)
                import cv2

                cv2.imwrite(str(d / f"{name}_color.png"), np.asarray(out["depth_color"]))
        elif kind == "segmentation":
            import cv2

            cls = np.asarray(out["classes"])
            cv2.imwrite(
                str(d / f"{name}.png"), cls.astype(np.uint8 if cls.max(initial=0) < 256 else np.uint16)
            )
        elif kind != "detection":
            np.savez(d / f"{name}.npz", **{k: np.asarray(v) for k, v in out.items()})
        self.written[h] += 1
        if self.viz:
            self._viz(kind, info, result, frame, d / "viz" / name)

    def _viz(
        self, kind: str, info: dict[str, Any], result: Result, frame: np.ndarray | None, stem: Path
    ) -> None:
        import cv2

        out = result.outputs
        if kind == "depth" and "depth" in out:
            cv2.imwrite(f"{stem}.png", visualize.colorize_depth(np.asarray(out["depth"])))
        elif kind == "segmentation" and frame is not None:
            pal = info.get("palette")
            cv2.imwrite(
                f"{stem}.jpg",
                visualize.overlay_segmentation(
                    frame, np.asarray(out["classes"]), None if pal is None else np.asarray(pal, np.uint8)
                ),
            )
        elif kind == "detection" and frame is not None:
            cv2.imwrite(
                f"{stem}.jpg",
                visualize.draw_detections(
                    frame,
                    np.asarray(out["boxes"]),
                    np.asarray(out["scores"]),
                    np.asarray(out["labels"]),
                    info.get("labels"),
                ),
            )

    def close(self) -> None:
        for f in self._jsonl.values():
            f.close()
        self._jsonl.clear()
