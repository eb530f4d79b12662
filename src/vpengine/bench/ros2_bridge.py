"""ROS 2 bridge throughput: 1080p bgr8 frames in over DDS at 30 Hz, every head's outputs out, on loopback.

Three parties: this process publishes ``sensor_msgs/Image`` frames (each with a unique stamp) at the target rate;
a subscriber process takes every output topic with ROS 2's default subscriber QoS (reliable, keep last 10) and does
real work on each sample (decodes it and copies its pixels, as a consumer would); the bridge (``vpengine ros2``)
runs in its own process with its engine. ``--load N`` keeps N more processes busy on the CPU for the whole run (a
machine partly loaded by other work). Counted per stage, so a loss is attributed to where it happened:

* transport in: frames published vs frames the bridge received (its ``/diagnostics`` counters);
* engine: frames each model ran on vs skipped (lossy by design when a model is slower than the input);
* transport out: outputs the bridge published vs outputs received here, per topic;
* end to end: outputs received per head vs frames published (1.0 = nothing lost anywhere).

Also measured: the CPU time of the bridge process and its engine workers (per frame), the engine's per-model
latencies, publish -> receive latency (p50, p99, max: whether outputs queue up), and the bridge's decode of one frame
per encoding against the numpy channel swap it replaced (``decode_ms``). Results go to ``<out>/<name>.json``.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import subprocess
import sys
import threading
import time
from typing import Any

import numpy as np

from vpengine.arguments import add_overrides_argument


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default="tiny", help="engine config (default: the shipped tiny config)")
    p.add_argument(
        "--sizes",
        default="1920x1080,640x480",
        help="frame sizes to run, WxH comma-separated (default: 1920x1080 and, to tell the bridge's limits from "
        "the engine's, 640x480)",
    )
    p.add_argument("--rate", type=float, default=30.0, help="frames per second published (default 30)")
    p.add_argument("--seconds", type=float, default=10.0, help="how long to publish (default 10)")
    p.add_argument(
        "--input-qos",
        choices=["sensor", "default"],
        default="sensor",
        help="input QoS of publisher and bridge: sensor (best effort, what cameras use; default) or default (reliable)",
    )
    p.add_argument(
        "--output-qos",
        default="latest",
        help="the bridge's output QoS (vpengine ros2 --output-qos): latest, default, or both comma-separated to "
        "compare them, each size run with each (default: latest)",
    )
    p.add_argument(
        "--load", type=int, default=0, help="extra processes keeping the CPU busy during the run (default 0)"
    )
    p.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="run every size and QoS this many times, interleaved (default 1)",
    )
    p.add_argument("--name", default="ros2_bridge_throughput", help="results file name (without .json)")
    p.add_argument("--mode", choices=["process", "thread"], default="process", help="engine mode")
    p.add_argument("--extras", action="store_true", help="also publish depth_color and seg overlay topics")
    p.add_argument("--domain-id", type=int, default=None, help="DDS domain (default: from the process id)")
    add_overrides_argument(p)


def _cpu_seconds(pid: int) -> tuple[float, float]:
    """User+system CPU seconds of a process, and of all its (live) descendants (the engine's workers)."""
    import psutil

    try:
        proc = psutil.Process(pid)
        kids = proc.children(recursive=True)
        t = proc.cpu_times()
        own = t.user + t.system
    except psutil.NoSuchProcess:
        return 0.0, 0.0
    total = 0.0
    for p in kids:
        try:
            t = p.cpu_times()
            total += t.user + t.system
        except psutil.NoSuchProcess:
            pass
    return own, total


def hog(stop: Any) -> None:
    """A process that keeps one core busy until ``stop`` is set (``--load``)."""
    n = 0
    while not stop.is_set():
        for _ in range(100_000):
            n += 1


def decode_ms(width: int, height: int, repeat: int = 15) -> dict[str, float]:
    """Median ms to decode one frame per encoding (:func:`vpengine.ros2.messages.image_to_frame`, to BGR), and of the
    numpy channel swap that decoded rgb8 before (``numpy_swap_rgb8``)."""
    from vpengine.ros2.messages import Header, image_to_frame
    from vpengine.ros2.outputs import image_out

    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    out = {}
    for enc, a in (("bgr8", img), ("rgb8", img), ("mono8", np.ascontiguousarray(img[..., 0]))):
        msg = image_out(a, enc, Header(0, 0))
        msg.data = bytes(msg.data)  # read-only, as received
        out[enc] = _median_ms(lambda m=msg: image_to_frame(m, "bgr"), repeat)
    view = np.frombuffer(bytes(img), np.uint8).reshape(img.shape)
    out["numpy_swap_rgb8"] = _median_ms(lambda: np.ascontiguousarray(view[..., ::-1]), repeat)
    return out


def _median_ms(f: Any, repeat: int) -> float:
    f()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def subscriber(conn: Any, domain: int, topics: list[str]) -> None:
    """The subscriber process: takes every output, copies its pixels (real work, as a consumer would), records
    (stamp, receive time), and keeps the last /diagnostics."""
    from vpengine.ros2 import cdr
    from vpengine.ros2 import dds_types as T
    from vpengine.ros2.dds import DdsContext

    ctx = DdsContext(domain)
    readers = {t: ctx.reader(t, T.Detection2DArray_ if t.endswith("/detections") else T.Image_) for t in topics}
    diag = ctx.reader("/diagnostics", T.DiagnosticArray_)
    while any(not r.dds.get_matched_publications() for r in readers.values()):
        time.sleep(0.05)
    conn.send("matched")
    # (stamp sec, stamp nanosec, time taken here, time the bridge wrote it)
    received: dict[str, list[tuple[int, int, float, float]]] = {t: [] for t in topics}
    last: Any = None

    def parsed() -> dict[str, dict[str, str]]:
        status = {}
        if last is not None:
            for st in last.status:
                status[st.name.split(": ", 1)[-1]] = {kv.key: kv.value for kv in st.values}
        return status

    while True:
        if conn.poll(0):
            if conn.recv() == "stop":
                break
            conn.send(parsed())  # "status": the newest diagnostics so far; keep counting
        got = False
        for t, r in readers.items():
            for raw, written in r.take_raw_stamped(64):
                got = True
                now = time.time()
                if t.endswith("/detections"):
                    m = T.Detection2DArray_.deserialize(raw)
                    received[t].append((m.header.stamp.sec, m.header.stamp.nanosec, now, written))
                else:
                    view = cdr.decode_image(raw)
                    view.data.copy()
                    received[t].append((view.header.sec, view.header.nanosec, now, written))
        for d in diag.take(16):
            last = d
        if not got:
            time.sleep(0.002)
    conn.send((received, parsed()))
    ctx.close()


def drained(status: dict[str, dict[str, str]], topics: list[str]) -> bool:
    """True when the bridge's diagnostics account for every head run: each output topic published it, or the
    result stream counted it missed, or a newer result of the head superseded it (nothing still on its way out of
    the bridge)."""
    iface = status.get("interface", {})
    for t in topics:
        head = t.split("/")[2]
        runs = status.get(head, {}).get("runs")
        published = iface.get(f"published:{t}")
        if runs is None or published is None:
            return False
        gone = int(iface.get(f"results_missed.{head}", "0")) + int(iface.get(f"outputs_superseded.{head}", "0"))
        if int(float(runs)) != int(published) + gone:
            return False
    return True


def _wait_drained(conn: Any, topics: list[str], least_s: float = 3.0, most_s: float = 30.0) -> float:
    """Wait (at least ``least_s``) until the subscriber's newest diagnostics show the bridge drained; seconds waited.

    At 1080p on two cores the bridge can still be converting and writing outputs seconds after the last input;
    a snapshot taken then makes runs look unaccounted for.
    """
    t0 = time.monotonic()
    time.sleep(least_s)
    while time.monotonic() - t0 < most_s:
        conn.send("status")
        if not conn.poll(10):
            raise RuntimeError("the subscriber process did not answer a status request within 10 s")
        if drained(conn.recv(), topics):
            break
        time.sleep(0.5)
    return time.monotonic() - t0


def measure(args: argparse.Namespace, width: int, height: int, output_qos: str) -> dict[str, Any]:
    from vpengine.ros2 import cdr
    from vpengine.ros2 import dds_types as T
    from vpengine.ros2.dds import DdsContext, loopback_config
    from vpengine.ros2.messages import Header
    from vpengine.ros2.outputs import image_out

    load_start = os.getloadavg()[0]
    domain = args.domain_id if args.domain_id is not None else 100 + os.getpid() % 120
    env = {**os.environ, "CYCLONEDDS_URI": loopback_config()}
    os.environ["CYCLONEDDS_URI"] = env["CYCLONEDDS_URI"]
    cmd = [
        sys.executable,
        "-m",
        "vpengine",  # the console script in a child process, not an import of cli/
        "ros2",
        "--config",
        args.config,
        "--input-topic",
        "/bench/image_raw",
        "--domain-id",
        str(domain),
        "--input-qos",
        args.input_qos,
        "--output-qos",
        output_qos,
        "--mode",
        args.mode,
        "--set",
        f"input.height={height}",
        "--set",
        f"input.width={width}",
    ]
    for o in args.overrides:
        cmd += ["--set", o]
    if args.extras:
        cmd += ["--depth-color", "--seg-overlay"]
    bridge = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    lines: list[str] = []
    try:
        assert bridge.stdout is not None
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            line = bridge.stdout.readline()
            if not line:
                raise RuntimeError("bridge exited before it was ready:\n" + "".join(lines[-30:]))
            lines.append(line)
            if line.startswith("vpengine ros2: ready"):
                break
        drain = threading.Thread(target=lambda: lines.extend(bridge.stdout or []), daemon=True)
        drain.start()
        topics = line.split("-> ", 1)[1].strip().split(", ")

        pub = DdsContext(domain)
        writer = pub.writer("/bench/image_raw", T.Image_, args.input_qos)
        ctx = multiprocessing.get_context("spawn")
        parent_end, child_end = ctx.Pipe()
        rx_proc = ctx.Process(target=subscriber, args=(child_end, domain, topics), daemon=True)
        rx_proc.start()
        if not parent_end.poll(120):
            raise RuntimeError("the subscriber process did not come up within 120 s")
        parent_end.recv()  # "matched": it sees the bridge's writers
        t_wait = time.monotonic() + 30
        while writer.matched() < 1:
            if time.monotonic() > t_wait:
                raise RuntimeError("DDS discovery (publisher -> bridge) did not complete within 30 s")
            time.sleep(0.05)
        time.sleep(0.5)

        stop_hogs = ctx.Event()
        hogs = [ctx.Process(target=hog, args=(stop_hogs,), daemon=True) for _ in range(args.load)]
        for h in hogs:
            h.start()
        sent_at: dict[tuple[int, int], float] = {}
        rng = np.random.default_rng(0)
        frames = [rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in range(4)]
        n = round(args.seconds * args.rate)
        cpu0 = _cpu_seconds(bridge.pid)
        t0 = time.monotonic()
        late = 0
        for i in range(n):
            target = t0 + i / args.rate
            while (now := time.monotonic()) < target:
                time.sleep(min(target - now, 0.005))
            if now - target > 1.0 / args.rate:
                late += 1
            h = Header(1_700_000_000 + i // 1000, (i % 1000) * 1_000_000 + 7, "bench_camera")
            msg = cdr.encode_image(image_out(frames[i % 4], "bgr8", h))
            sent_at[(h.sec, h.nanosec)] = time.time()
            writer.write_raw(msg)
        pub_wall = time.monotonic() - t0
        drain_s = _wait_drained(parent_end, topics)  # let the pipeline drain
        cpu1 = _cpu_seconds(bridge.pid)
        stop_hogs.set()
        for h in hogs:
            h.join(10)
        parent_end.send("stop")
        if not parent_end.poll(60):
            raise RuntimeError("the subscriber process did not report within 60 s")
        received, last_status = parent_end.recv()
        rx_proc.join(10)
    finally:
        bridge.send_signal(2)
        try:
            bridge.wait(60)
        except subprocess.TimeoutExpired:
            bridge.kill()
            bridge.wait(10)
    pub.close()

    status: dict[str, dict[str, str]] = last_status
    iface = status.get("interface", {})
    per_topic = {}
    for t in topics:
        stamps = received.get(t, [])
        lat = [rx_t - sent_at[(s, ns)] for s, ns, rx_t, _ in stamps if (s, ns) in sent_at]
        out = [rx_t - wr_t for _, _, rx_t, wr_t in stamps]
        per_topic[t] = {
            "received": len(stamps),
            "published_by_bridge": int(iface.get(f"published:{t}", -1)),
            "unknown_stamps": sum((s, ns) not in sent_at for s, ns, _, _ in stamps),
            "fraction_of_frames": len(stamps) / n if n else 0.0,
            "latency_ms": {
                "p50": float(np.percentile(lat, 50) * 1e3) if lat else None,
                "p99": float(np.percentile(lat, 99) * 1e3) if lat else None,
                "max": float(np.max(lat) * 1e3) if lat else None,
            },
            # the last hop alone: the bridge's write -> taken by the subscriber (where outputs queue, if they do)
            "write_to_take_ms": {
                "p50": float(np.percentile(out, 50) * 1e3) if out else None,
                "p99": float(np.percentile(out, 99) * 1e3) if out else None,
                "max": float(np.max(out) * 1e3) if out else None,
            },
        }
    interface = status.get("interface", {})
    models = {
        name: {
            **{k: v.get(k) for k in ("runs", "skipped", "drops", "errors", "latency_p50_ms", "latency_p99_ms")},
            # outputs the engine produced that the bridge did not collect in time (counted by the engine)
            **(
                {
                    "results_missed": interface.get(f"results_missed.{name}", "0"),
                    # results the bridge did not publish because a newer one of the head was already there
                    "outputs_superseded": interface.get(f"outputs_superseded.{name}", "0"),
                }
                if name != "foundation"
                else {}
            ),
        }
        for name, v in status.items()
        if name != "interface"
    }
    bridge_cpu = (cpu1[0] - cpu0[0]) + (cpu1[1] - cpu0[1])
    main_cpu = cpu1[0] - cpu0[0]
    # The bridge's CPU per stage (thread CPU time, so not inflated by other load): input stages per submitted
    # frame, output stages per frame whose outputs went out (the busiest head's runs).
    submitted = max(int(iface.get("submitted", 0)), 1)
    processed = max([int(m.get("runs") or 0) for n, m in status.items() if n not in ("interface", "foundation")] + [1])
    busy_s = {k.split(".", 1)[1]: float(v) for k, v in iface.items() if k.startswith("busy_s.")}
    per_in = {k: busy_s.get(k, 0.0) / submitted * 1e3 for k in ("decode", "resize", "submit")}
    per_out = {k: busy_s.get(k, 0.0) / processed * 1e3 for k in ("results", "convert", "encode", "write")}
    return {
        "config": args.config,
        "frame": f"{width}x{height} bgr8",
        "target_hz": args.rate,
        "seconds": args.seconds,
        "mode": args.mode,
        "input_qos": args.input_qos,
        "output_qos": output_qos,
        "subscriber": "another process; ROS 2 default QoS (reliable, keep last 10); decodes and copies each image",
        "load_processes": args.load,
        "extras": args.extras,
        "overrides": args.overrides,
        "frames_published": n,
        "publish_hz": n / pub_wall,
        "publisher_late_frames": late,
        "bridge_received": int(iface.get("received", -1)),
        "bridge_submitted": int(iface.get("submitted", -1)),
        "models": models,
        "topics": per_topic,
        "lossless": all(v["received"] == n for v in per_topic.values()),
        "process_tree_cpu_s": bridge_cpu,
        "process_tree_cpu_cores": bridge_cpu / (pub_wall + drain_s),
        "bridge_process_cpu_cores": main_cpu / (pub_wall + drain_s),
        "engine_workers_cpu_cores": (bridge_cpu - main_cpu) / (pub_wall + drain_s),
        "drain_s": drain_s,
        "bridge_superseded": int(iface.get("superseded", 0)),
        "bridge_cpu_ms_per_input_frame": per_in,
        "bridge_cpu_ms_per_output_frame": per_out,
        # carrying one frame in and all of its outputs out: the bridge alone could sustain 1000 / this Hz on a core
        "bridge_cpu_ms_per_frame_in_and_out": sum(per_in.values()) + sum(per_out.values()),
        # the machine may be shared: the 1-minute load average before the bridge started and after the run
        "load_average_1m_at_start": load_start,
        "load_average_1m_at_end": os.getloadavg()[0],
        "decode_ms": decode_ms(width, height),
        "bridge_log_tail": "".join(lines[-15:]),
    }


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v:.0f}"


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"size {text!r} is not WIDTHxHEIGHT (e.g. 1920x1080)") from None
    return w, h


def main(args: argparse.Namespace) -> int:
    from vpengine.bench.common import write_results
    from vpengine.ros2.outputs import OUTPUT_QOS

    profiles = [q.strip() for q in args.output_qos.split(",") if q.strip()]
    for q in profiles:
        if q not in OUTPUT_QOS:
            raise ValueError(f"output QoS {q!r} is not known; accepted: {', '.join(OUTPUT_QOS)}")
    if args.repeat < 1:
        raise ValueError(f"--repeat must be >= 1, got {args.repeat}")
    sizes = [_size(sz) for sz in args.sizes.split(",") if sz.strip()]
    runs = [measure(args, w, h, q) for _ in range(args.repeat) for w, h in sizes for q in profiles]
    path = write_results(args.out, args.name, {"runs": runs})
    for res in runs:
        print(
            f"{res['frame']} at {res['target_hz']:g} Hz for {res['seconds']:g} s ({res['mode']} mode, input QoS "
            f"{res['input_qos']}, output QoS {res['output_qos']}, {res['load_processes']} CPU hogs): published "
            f"{res['frames_published']}, bridge received {res['bridge_received']}, "
            f"submitted {res['bridge_submitted']} (superseded {res['bridge_superseded']}); CPU: bridge process "
            f"{res['bridge_process_cpu_cores']:.2f} cores, engine workers {res['engine_workers_cpu_cores']:.2f} "
            f"cores; load avg {res['load_average_1m_at_start']:.1f} before, {res['load_average_1m_at_end']:.1f} after"
        )
        stages = {**res["bridge_cpu_ms_per_input_frame"], **res["bridge_cpu_ms_per_output_frame"]}
        print(
            f"  bridge CPU per frame in and out: {res['bridge_cpu_ms_per_frame_in_and_out']:.1f} ms ("
            + ", ".join(f"{k} {v:.1f}" for k, v in stages.items())
            + ")"
        )
        for name, m in res["models"].items():
            print(f"  model {name:10s} runs {m['runs']:>5s} skipped {m['skipped']:>5s} p50 {m['latency_p50_ms']} ms")
        for t, v in res["topics"].items():
            print(
                f"  {t:32s} received {v['received']:4d}/{res['frames_published']} (bridge published "
                f"{v['published_by_bridge']}), latency p50 / p99 / max {_ms(v['latency_ms']['p50'])} / "
                f"{_ms(v['latency_ms']['p99'])} / {_ms(v['latency_ms']['max'])} ms (write -> take "
                f"{_ms(v['write_to_take_ms']['p50'])} / {_ms(v['write_to_take_ms']['p99'])} / "
                f"{_ms(v['write_to_take_ms']['max'])} ms)"
            )
        print(f"  lossless end to end: {res['lossless']}")
        print("  decode ms per frame: " + ", ".join(f"{k} {v:.2f}" for k, v in res["decode_ms"].items()))
    print(f"-> {path}")
    return 0
