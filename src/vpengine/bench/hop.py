"""Mailbox hop: writer publishes -> reader (another process) is woken -> reader has the slot pinned.

The writer fills a feature-sized slot, publishes it and waits for the reader's acknowledgement before the next
one, so every sample is one isolated hop (latency, not throughput). Times are CLOCK_MONOTONIC in both processes.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--hops", type=int, default=10000, help="number of hops (default 10000)")
    p.add_argument("--mbytes", type=float, default=4.0, help="payload size in MB (default 4)")
    p.add_argument("--device", default="cpu", help="where the slots live: cpu (host shared memory) or cuda")
    p.add_argument(
        "--layout",
        choices=["flat", "vits-1080p"],
        default="flat",
        help="flat: four tensors of --mbytes in all; vits-1080p: DINOv2 ViT-S features of a 1080p frame "
        "(4 layers x [2442, 384] patch + CLS tokens, float32, 15 MB)",
    )


def _specs(mbytes: float, layout: str = "flat") -> dict[str, Any]:
    from vpengine.specs import TensorSpec

    if layout == "vits-1080p":  # 1920x1080 -> 924x518 -> 66x37 tokens
        specs = {f"patch.{i}": TensorSpec((66 * 37, 384), "float32") for i in range(4)}
        specs.update({f"cls.{i}": TensorSpec((384,), "float32") for i in range(4)})
        return specs
    per = int(mbytes * 1e6 / 4 / 4)  # four float32 tensors
    return {f"patch.{i}": TensorSpec((per,), "float32") for i in range(4)}


def _reader(fd: int) -> None:
    from vpengine.runtime.process import recv_fds
    from vpengine.transport.ring import SlotRing

    conn = Connection(fd)
    desc, n = conn.recv()
    fds = recv_fds(conn)
    ring = SlotRing.attach(desc, fds)
    reader = ring.reader("head")
    hops = np.empty(n)
    conn.send("ready")
    for i in range(n):
        slot = reader.pin(timeout=10.0)
        t = time.monotonic()
        if slot is None:
            conn.send(("error", f"no slot after 10 s at hop {i}"))
            return
        hops[i] = t - slot.t_publish
        reader.release(slot)
        conn.send_bytes(b"a")
    conn.send(("hops", hops))


def measure(n: int, mbytes: float, device: str = "cpu", layout: str = "flat") -> dict[str, Any]:
    import torch

    from vpengine.runtime.process import package_env, send_fds
    from vpengine.transport.ring import ReaderDecl, SlotRing

    specs = _specs(mbytes, layout)
    ring = SlotRing.create("hop", specs, 3, [ReaderDecl("head")], device, shared=True)
    ours, theirs = socket.socketpair()
    proc = subprocess.Popen(
        [sys.executable, "-m", "vpengine.bench.hop", "--child", str(theirs.fileno())],
        pass_fds=[theirs.fileno()],
        env=package_env(),
    )
    theirs.close()
    conn = Connection(ours.detach())
    try:
        fds: list[int] = []
        desc = ring.export(fds)
        conn.send((desc, n))
        send_fds(conn, fds)
        assert conn.recv() == "ready"
        writer = ring.writer()
        for i in range(n):
            slot = writer.acquire()
            assert slot is not None
            for t in slot.tensors.values():
                t.fill_(float(i))
            if device != "cpu":
                torch.cuda.synchronize()  # publish only complete work (not part of the hop)
            writer.publish(slot, i, 0.0, time.monotonic())
            conn.recv_bytes()
        kind, hops = conn.recv()
        if kind != "hops":
            raise RuntimeError(hops)
    finally:
        proc.wait(10)
        conn.close()
        ring.close()
    us = hops * 1e6
    return {
        "hops": n,
        "payload_bytes": int(sum(s.nbytes for s in specs.values())),
        "device": device,
        "layout": layout,
        "median_us": float(np.median(us)),
        "p90_us": float(np.percentile(us, 90)),
        "p99_us": float(np.percentile(us, 99)),
        "mean_us": float(us.mean()),
        "max_us": float(us.max()),
        "samples_us": [round(float(v), 2) for v in us],
    }


def main(args: argparse.Namespace) -> int:
    from vpengine.bench.common import write_results

    r = measure(args.hops, args.mbytes, args.device, args.layout)
    samples = r.pop("samples_us")
    suffix = "" if args.layout == "flat" else f"_{args.layout}"
    path = write_results(args.out, f"hop_{args.device.replace(':', '')}{suffix}", r)
    _figure(samples, r, path.with_suffix(".png"))
    print(
        f"mailbox hop over {r['hops']} hops, {r['payload_bytes'] / 1e6:.1f} MB slots on {args.device}: "
        f"median {r['median_us']:.1f} us, p99 {r['p99_us']:.1f} us, max {r['max_us']:.0f} us -> {path}"
    )
    return 0


def _figure(samples: list[float], r: dict[str, Any], path: Any) -> None:
    from vpengine.bench.common import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.2), dpi=120)
    a = np.asarray(samples)
    ax.hist(a[a <= np.percentile(a, 99.5)], bins=80, color="#3b7dd8")
    for q, style in ((r["median_us"], "-"), (r["p99_us"], "--")):
        ax.axvline(q, color="k", ls=style, lw=1)
    ax.set_xlabel("publish -> reader pinned (us)")
    ax.set_ylabel("hops")
    ax.set_title(f"mailbox hop: median {r['median_us']:.0f} us, p99 {r['p99_us']:.0f} us")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__" and len(sys.argv) == 3 and sys.argv[1] == "--child":
    _reader(int(sys.argv[2]))
    os._exit(0)
