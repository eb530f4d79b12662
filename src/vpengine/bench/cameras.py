"""Several cameras on one engine (Note [Cameras] in runtime/worker.py) against one engine a camera.

Two measurements, on the config's models (``configs/bench.yaml`` by default: DINOv2 ViT-S/14 + depth, segmentation
and detection heads at 1080p, process mode; ``--set`` as everywhere):

* ``stream``: ``--stream-cameras`` cameras (4) at ``--fps`` each (30 Hz), for ``--seconds``, each camera's frames
  submitted by a thread of its own at every tick, as synchronised cameras' drivers deliver them: per frame, the
  latency from submit to every head's result on the host (p50, p99), frames some head never answered (each is
  counted by the engine too, as skipped), how long the cameras take to hand in a tick's frames (``tick_submit_ms``,
  from the tick's start to the last submit's return: an upper bound on how far apart they reach the backbone; a frame
  that comes past the batch window runs in the next batch, counted late), the engine's start (``start_s``), the
  device memory in use (NVML, else PyTorch's reserved bytes) with the engine's memory report, where frames missed a
  head and the slowest ticks, and the host page faults each thread and worker process took over the first second and
  the rest (``page_faults``; Linux): a thread that serves without mapping new memory takes none.
* ``throughput``: for each N in ``--cameras`` (1, 2, 4, 8), frames per second through every head, as fast as they go,
  each camera pumped by its own thread with as many frames in flight as a file run keeps (Note [Frames in flight]
  in pipeline/pacing.py: every frame through every head, in order; the count is in the results), ``--rounds``
  frames a camera and for ``--point-seconds`` at least: one engine with N cameras (batched) against N engines of one
  camera each running side by side in this process (the GPU overlaps their streams). Their ratio is what batching
  buys. A frame that came back without some head's output is not counted but reported (``frames_missing_a_head``);
  the batched engine's counts over the point (``batched_engine_counted``: frames run, late for their batch, deferred,
  run with another camera's, model calls) say how full its batches were. Where a frame's time goes, for each
  (``frame_ms``): from its submit to the last head's result being there (``ready``: the engine's and device's work,
  and the queue before them), and from then, or from the wait call if later, to the wait's return (``read``:
  copying the results out, and waiting for another caller's). With one frame in flight a camera's next
  frame waited for its last one's every result, so one engine ran its stages one batch after the other while N
  engines overlapped theirs: that measured latency, not throughput.

::

    vpengine bench cameras --set device=cpu -c configs/tiny.yaml --cameras 1,2 --seconds 3   # anywhere
    vpengine bench cameras                                                                     # a GPU machine
"""

from __future__ import annotations

import argparse
import collections
import threading
import time
from typing import Any

import numpy as np

from vpengine.arguments import add_overrides_argument


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", "-c", default="bench", help="engine config (default: the shipped bench config)")
    add_overrides_argument(p, "mode=thread")
    p.add_argument("--stream-cameras", type=int, default=4, help="cameras of the stream run (default 4; 0: skip)")
    p.add_argument("--fps", type=float, default=30.0, help="each camera's rate in the stream run (default 30 Hz)")
    p.add_argument("--seconds", type=float, default=10.0, help="length of the stream run (default 10 s)")
    p.add_argument("--cameras", default="1,2,4,8", help="camera counts of the throughput sweep (default 1,2,4,8)")
    p.add_argument(
        "--rounds", type=int, default=60, help="frames a camera in each throughput point, at least (default 60)"
    )
    p.add_argument(
        "--point-seconds",
        type=float,
        default=3.0,
        help="each throughput point runs at least this long (default 3 s: a point of a fraction of a second is noise)",
    )
    p.add_argument("--heads", default=None, help="the config's heads to run, comma separated (default: all)")
    p.add_argument("--name", default=None, help="results file name (default: cameras_<device>)")


def _config(base: Any, cameras: int) -> Any:
    from vpengine.config import load_config

    data = base.model_dump()
    data["cameras"] = [{"name": f"cam{i}"} for i in range(cameras)] if cameras > 1 else []
    return load_config(data)


def _device_memory(engine: Any) -> int | None:
    """Device memory the engine uses: this process's and, in process mode, its workers'."""
    import os

    import torch

    if not str(engine.config.device).startswith("cuda"):
        return None
    from vpengine.runtime.gpu import process_memory

    by_pid = process_memory(torch.device(engine.config.device).index or 0)
    if by_pid:
        pids = {os.getpid(), *(s["pid"] for s in engine.stats()["models"].values())}
        if not pids & by_pid.keys():  # NVML sees other pids (another pid namespace): no figure rather than 0
            return None
        return sum(by_pid.get(pid, 0) for pid in pids)
    return int(torch.cuda.memory_reserved())


def stream(base: Any, n: int, fps: float, seconds: float, imgs: list[np.ndarray]) -> dict[str, Any]:
    from vpengine.bench.paper.harness import log, pct
    from vpengine.engine import Engine

    t_start = time.monotonic()
    with Engine(_config(base, n)) as eng:
        # a first start compiles and captures (Note [Start progress] in runtime/supervisor.py)
        start_s = time.monotonic() - t_start
        cams = eng.cameras
        heads = list(eng.plan.heads)
        for i in range(10):  # warm-up, every camera
            for c in cams:
                eng.wait(eng.submit(imgs[i % len(imgs)], camera=c), timeout=120)
        eng.results()
        warm = _counted(eng.stats())  # the warm-up's frames, one at a time, each waiting the window: not counted
        frames: dict[int, dict[str, float]] = {}
        where: dict[int, tuple[int, int]] = {}  # frame id: its tick, its camera's index
        handing: list[float] = []  # per tick: its start to the last submit's return, s
        submitted = 0
        workers: dict[int, list[str]] = {}  # pid -> its models
        for model, st in eng.stats()["models"].items():
            workers.setdefault(int(st["pid"]), []).append(model)
        faults = [_page_faults(workers)]  # at the stream's start, after its first second, at its end
        t0 = time.monotonic()
        with _Cameras(eng, cams, imgs) as drivers:
            k = 0
            while time.monotonic() - t0 < seconds:
                t = t0 + k / fps
                while (now := time.monotonic()) < t:
                    for r in eng.results(timeout=t - now):
                        frames.setdefault(r.frame_id, {})[r.head] = r.latency
                if k == round(fps):  # a second in
                    faults.append(_page_faults(workers))
                t_hand = time.monotonic()
                for i, fid in enumerate(drivers.tick(k, time.time())):  # synchronised cameras: one stamp a tick
                    frames.setdefault(fid, {})
                    where[fid] = (k, i)
                    submitted += 1
                handing.append(time.monotonic() - t_hand)
                k += 1
            faults.append(_page_faults(workers))  # the cameras' threads still there
        ticks = k
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            rs = eng.results(timeout=0.5)
            if not rs:
                break
            for r in rs:
                frames.setdefault(r.frame_id, {})[r.head] = r.latency
        memory = _device_memory(eng)
        st = eng.stats()
        for _ in range(100):  # until the backbone has accounted for every frame (ran, skipped or dropped), 5 s at most
            fm = _counted(st, since=warm)["foundation"]
            if fm["runs"] + fm["skipped"] + fm["dropped"] >= submitted:
                break
            time.sleep(0.05)
            st = eng.stats()
    # the stream's frames (not the warm-up's): their latency through every head; where the misses and the tail
    # were, at the start (something done once) or spread over the stream
    whole: list[float] = []  # s
    missed: list[tuple[int, int]] = []  # tick, camera index
    worst: dict[int, float] = {}  # tick: its slowest frame's latency, s
    for f, (k, i) in where.items():
        v = frames[f]
        if len(v) == len(heads):
            whole.append(max(v.values()))
        else:
            missed.append((k, i))
        if v:
            worst[k] = max(worst.get(k, 0.0), *v.values())
    missed.sort()
    out = {
        "cameras": n,
        "fps_per_camera": fps,
        "seconds": seconds,
        "start_s": start_s,
        "frames_submitted": submitted,
        "frames_all_heads": len(whole),
        "frames_not_all_heads": submitted - len(whole),
        "latency_all_heads_ms": pct(whole),
        "tick_submit_ms": pct(handing),  # against the batch window: ``counted``'s late
        # the first 100 frames that missed a head, as [tick, camera]; the 10 ticks whose slowest frame took longest
        "missed_frames": [[k, cams[i]] for k, i in missed[:100]],
        "slowest_ticks_ms": sorted(([k, 1e3 * s] for k, s in worst.items()), key=lambda t: -t[1])[:10],
        "device_memory_bytes": memory,
        "memory_report": st["memory"],  # where it goes: mailboxes, each worker's pool, each process's (at start)
        "workers_on_mps": len(st["engine"]["mps"]["workers_on_mps"]),  # MPS overlaps the workers' kernels
        "counted": _counted(st, since=warm),  # over the stream
        # what each thread of this process (by name) and each worker process took (Note [First batch] in
        # runtime/worker.py: serving maps no new memory), over the stream's first second and over the rest
        # (None where /proc cannot tell; a stream of fewer than ``fps`` ticks: all of it the first second)
        "page_faults": None
        if faults[0] is None
        else {
            "first_second": _faults_between(faults[0], faults[1]),
            "rest": _faults_between(faults[1], faults[2]) if len(faults) > 2 else None,
        },
    }
    fm = out["counted"]["foundation"]
    log(
        f"stream: {n} cameras at {fps:g} Hz, {len(whole)}/{submitted} frames through every head, "
        f"p50 {out['latency_all_heads_ms']['p50']:.1f} ms, p99 {out['latency_all_heads_ms']['p99']:.1f} ms, "
        f"a tick's submits p99 {out['tick_submit_ms']['p99']:.1f} ms, the backbone's mean batch "
        f"{fm['runs'] / max(fm['batches'], 1):.1f} frames ({fm['late']} late), "
        f"device memory {memory / 2**30 if memory else float('nan'):.2f} GiB, {out['workers_on_mps']} workers on MPS; "
        f"missed a head at ticks {_listed(sorted({k for k, _ in missed}))}, slowest ticks "
        f"{', '.join(f'{k} ({ms:.0f} ms)' for k, ms in out['slowest_ticks_ms'][:5])} of {ticks}"
    )
    for span, taken in (out["page_faults"] or {}).items():
        if taken is not None:
            most = ", ".join(f"{k} {v}" for k, v in list(taken.items())[:6]) or "none"
            log(f"stream: host page faults, {span.replace('_', ' ')}: {most}")
    return out


def _page_faults(workers: dict[int, list[str]]) -> dict[str, int] | None:
    """Minor page faults so far (Linux; None elsewhere): of each thread of this process by its Python name (threads
    Python did not start, such as the CUDA driver's, summed as "other"), and of each worker process in ``workers``
    (pid -> its models) other than this one, as "process <models>". A first touch of memory is one; memory that
    serving reuses takes none."""
    import os

    from vpengine.bench.common import proc_stat

    def minflt(stat_path: str) -> int:
        return int(proc_stat(stat_path)[7])  # state, ppid, pgrp, session, tty_nr, tpgid, flags, minflt

    names = {t.native_id: t.name for t in threading.enumerate()}
    out: dict[str, int] = {}
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return None
    for tid in tids:
        try:
            n = minflt(f"/proc/self/task/{tid}/stat")
        except (OSError, ValueError, IndexError):  # ended meanwhile
            continue
        name = names.get(int(tid), "other")
        out[name] = out.get(name, 0) + n
    for pid, models in workers.items():
        if pid != os.getpid():
            try:
                out[f"process {'+'.join(models)}"] = minflt(f"/proc/{pid}/stat")
            except (OSError, ValueError, IndexError):
                continue
    return out


def _faults_between(before: dict[str, int] | None, after: dict[str, int] | None) -> dict[str, int]:
    """The faults each thread or process took between two ``_page_faults``, most first, those that took none left
    out (a thread started in between counts from its start)."""
    before, after = before or {}, after or {}
    taken = {k: n - before.get(k, 0) for k, n in after.items() if n > before.get(k, 0)}
    return dict(sorted(taken.items(), key=lambda kv: -kv[1]))


def _listed(ticks: list[int], most: int = 20) -> str:
    """``ticks`` for a log line: the first ``most`` and how many more, or "none"."""
    if not ticks:
        return "none"
    more = f" and {len(ticks) - most} more" if len(ticks) > most else ""
    return ", ".join(map(str, ticks[:most])) + more


class _Cameras:
    """A thread a camera, as a camera's driver delivers its frames: at each ``tick`` every camera submits one frame
    (the tick's ``k``-th of ``imgs``, shifted by the camera's index) stamped with the tick's capture time, at once;
    ``tick`` returns their frame ids when every camera's submit has returned, or raises a camera's error."""

    def __init__(self, eng: Any, cams: list[str], imgs: list[np.ndarray]) -> None:
        self.eng, self.cams, self.imgs = eng, cams, imgs
        # a submit never blocks on the models: a tick that has not gone through in this long has hung
        self._go = threading.Barrier(len(cams) + 1, timeout=60)
        self._done = threading.Barrier(len(cams) + 1, timeout=60)
        self._k, self._stamp = 0, 0.0
        self._fids: list[int] = [0] * len(cams)
        self._error: BaseException | None = None
        self._threads = [
            threading.Thread(target=self._drive, args=(i,), name=f"camera-{c}", daemon=True) for i, c in enumerate(cams)
        ]

    def __enter__(self) -> _Cameras:
        for t in self._threads:
            t.start()
        return self

    def _drive(self, i: int) -> None:
        try:
            while True:
                self._go.wait()
                img = self.imgs[(self._k + i) % len(self.imgs)]
                self._fids[i] = self.eng.submit(img, timestamp=self._stamp, camera=self.cams[i])
                self._done.wait()
        except threading.BrokenBarrierError:
            return
        except BaseException as e:  # handed to the tick, which raises it
            self._error = e
            self._go.abort()
            self._done.abort()

    def tick(self, k: int, stamp: float) -> list[int]:
        self._k, self._stamp = k, stamp
        try:
            self._go.wait()
            self._done.wait()
        except threading.BrokenBarrierError:
            raise RuntimeError(
                f"a camera's submit failed: {self._error!r}" if self._error else "a camera's submit hung for 60 s"
            ) from self._error
        return list(self._fids)

    def __exit__(self, *exc: object) -> None:
        self._go.abort()  # every driver returns: from its wait, or from its submit at the next one
        self._done.abort()
        for t in self._threads:
            t.join(timeout=10)


class _Pump:
    """One camera's frames, ``in_flight`` at most submitted and not yet answered, ``rounds`` frames and until
    ``until``: how many came back from every one of ``heads`` (``whole``), how many without some head's output
    (``torn``: overwritten before it was read, which a pump that ran far ahead of another camera's can cause), or
    the error that ended it."""

    def __init__(self, eng: Any, camera: str | None, heads: set[str], in_flight: int) -> None:
        self.eng, self.camera, self.heads, self.in_flight = eng, camera, heads, in_flight
        self.whole = self.torn = 0
        self.ready_s: list[float] = []  # per whole frame: submit -> the last head's result there
        self.read_s: list[float] = []  # per whole frame: then (or the wait call, if later) -> the wait's return
        self.error: Exception | None = None

    def _answer(self, fid: int, t_submit: float) -> None:
        t_call = time.monotonic()
        res = self.eng.wait(fid, timeout=120)
        t_back = time.monotonic()
        if set(res) >= self.heads:
            self.whole += 1
            ready = max(r.t_publish for r in res.values())
            self.ready_s.append(ready - t_submit)
            self.read_s.append(t_back - max(t_call, ready))
        else:
            self.torn += 1

    def run(self, imgs: list[np.ndarray], rounds: int, until: float) -> None:
        k = 0
        pending: collections.deque[tuple[int, float]] = collections.deque()
        try:
            while k < rounds or time.monotonic() < until:
                if len(pending) == self.in_flight:
                    self._answer(*pending.popleft())
                t = time.monotonic()
                pending.append((self.eng.submit(imgs[k % len(imgs)], camera=self.camera), t))
                k += 1
            while pending:
                self._answer(*pending.popleft())
        except Exception as e:
            self.error = e


def _all_cameras(
    pairs: list[tuple[Any, str | None]],
    imgs: list[np.ndarray],
    rounds: int,
    seconds: float,
    in_flight: int,
    heads: set[str],
) -> tuple[float, int, int, dict[str, list[float]]]:
    """Every camera pumped by its own thread, as each camera's driver would, ``rounds`` frames each and ``seconds``
    at least: frames per second through every head over them all, how many frames that is, how many missed some
    head, and where the whole frames' time went: each one's ``ready`` and ``read`` seconds (``frame_ms`` in the
    module's docstring)."""
    pumps = [_Pump(e, c, heads, in_flight) for e, c in pairs]
    t = time.monotonic()
    threads = [threading.Thread(target=p.run, args=(imgs, rounds, t + seconds)) for p in pumps]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    took = time.monotonic() - t
    errors = [p.error for p in pumps if p.error is not None]
    if errors:
        raise RuntimeError(
            f"{len(errors)} of {len(pairs)} cameras' pumps failed: {type(errors[0]).__name__}: {errors[0]}"
        ) from errors[0]
    whole = sum(p.whole for p in pumps)
    spent = {"ready": [v for p in pumps for v in p.ready_s], "read": [v for p in pumps for v in p.read_s]}
    return whole / took, whole, sum(p.torn for p in pumps), spent


COUNTED = ("runs", "skipped", "dropped", "late", "deferred", "batched", "batches")


def _counted(stats: dict[str, Any], since: dict[str, Any] | None = None) -> dict[str, dict[str, int]]:
    """Each model's frames run, skipped, dropped, late for their batch, deferred and run with another camera's
    (Note [Cameras]), from ``stats()``; with ``since`` (an earlier ``_counted``), what was added after it."""
    now = {m: {k: s[k] for k in COUNTED} for m, s in stats["models"].items()}
    if since is None:
        return now
    return {m: {k: v - since.get(m, {}).get(k, 0) for k, v in c.items()} for m, c in now.items()}


def throughput(base: Any, n: int, rounds: int, imgs: list[np.ndarray], seconds: float = 0.0) -> dict[str, Any]:
    """Frames per second through every head with a thread per camera, each keeping a file run's frames in flight
    (Note [Frames in flight]): one engine with ``n`` cameras (batched) against ``n`` one-camera engines side by
    side, each point ``seconds`` at least."""
    from vpengine.bench.paper.harness import engines, log, pct
    from vpengine.pipeline.pacing import pipelined

    one, in_flight = pipelined(_config(base, n))
    heads = {h.name for h in base.heads}
    with engines([one]) as (eng,):
        cams = eng.cameras if n > 1 else [None]
        _all_cameras([(eng, c) for c in cams], imgs, 5, 0.0, in_flight, heads)
        before = _counted(eng.stats())
        batched, _, batched_torn, batched_s = _all_cameras(
            [(eng, c) for c in cams], imgs, rounds, seconds, in_flight, heads
        )
        counted = _counted(eng.stats(), since=before)  # how full its batches were: late, deferred, batched
    with engines([pipelined(_config(base, 1))[0] for _ in range(n)]) as es:
        _all_cameras([(e, None) for e in es], imgs, 5, 0.0, in_flight, heads)
        separate, _, separate_torn, separate_s = _all_cameras(
            [(e, None) for e in es], imgs, rounds, seconds, in_flight, heads
        )
    torn = (
        f"; frames some head's output missed: {batched_torn} and {separate_torn}"
        if batched_torn + separate_torn
        else ""
    )
    frame_ms = {
        k: {what: pct(v) for what, v in s.items()} for k, s in (("batched", batched_s), ("separate", separate_s))
    }
    batched_ms, separate_ms = frame_ms["batched"], frame_ms["separate"]
    f = counted.get("foundation", {})
    log(
        f"throughput, {n} cameras, {in_flight} frames a camera in flight: one engine {batched:.1f} frames/s, "
        f"{n} engines {separate:.1f} frames/s{torn}; the one engine's backbone: {f.get('runs', 0)} frames, "
        f"{f.get('batched', 0)} with another camera's, {f.get('late', 0)} late, {f.get('deferred', 0)} deferred; "
        f"a frame's results there {batched_ms['ready']['p50']:.1f} and {separate_ms['ready']['p50']:.1f} ms after "
        f"its submit, read in {batched_ms['read']['p50']:.2f} and {separate_ms['read']['p50']:.2f} ms (p50)"
    )
    return {
        "cameras": n,
        "in_flight": in_flight,
        "batched_fps": batched,
        "separate_fps": separate,
        "ratio": batched / separate,
        "frames_missing_a_head": {"batched": batched_torn, "separate": separate_torn},
        "frame_ms": frame_ms,
        "batched_engine_counted": counted,
    }


def main(args: argparse.Namespace) -> int:
    from vpengine.bench.common import write_results
    from vpengine.bench.paper.harness import Bench
    from vpengine.config import load_config

    if args.point_seconds < 0 or args.rounds < 1:
        raise ValueError(f"--rounds {args.rounds}, --point-seconds {args.point_seconds}: at least 1 and 0")
    base = load_config(args.config, list(args.overrides))
    if args.heads:
        wanted = [h.strip() for h in args.heads.split(",") if h.strip()]
        names = [h.name for h in base.heads]
        unknown = [h for h in wanted if h not in names]
        if unknown or not wanted:
            raise ValueError(f"--heads {args.heads!r}: the config's heads are {', '.join(names)}")
        base = load_config(base.model_dump() | {"heads": [h.model_dump() for h in base.heads if h.name in wanted]})
    imgs = Bench(base).images()
    res: dict[str, Any] = {
        "config": args.config,
        "overrides": list(args.overrides),
        "mode": base.mode,
        "heads": [h.name for h in base.heads],
        "point_seconds": args.point_seconds,
        "throughput": [],
    }
    name = args.name or f"cameras_{str(base.device).split(':')[0]}"
    # the file is rewritten after each measurement: a run cut short keeps what it measured
    if args.stream_cameras:
        res["stream"] = stream(base, args.stream_cameras, args.fps, args.seconds, imgs)
        write_results(args.out, name, res)
    for n in (int(x) for x in args.cameras.split(",") if x.strip()):
        res["throughput"].append(throughput(base, n, args.rounds, imgs, args.point_seconds))
        path = write_results(args.out, name, res)
    print(path if res["throughput"] else write_results(args.out, name, res))
    return 0
