"""A slow reader in its own process: pins slots, checks their content twice with a pause in between."""

from __future__ import annotations

import sys
import time
from multiprocessing.connection import Connection

import torch


def expected_value(seq: int) -> float:
    return float(seq % 9973)


def main(fd: int) -> None:
    from vpengine.runtime.process import recv_fds
    from vpengine.transport.ring import SlotRing

    conn = Connection(fd)
    desc, name, hold_s, duration = conn.recv()
    ring = SlotRing.attach(desc, recv_fds(conn))
    reader = ring.reader(name)
    conn.send("ready")
    reads = torn = 0
    last = 0
    t_end = time.monotonic() + duration
    while time.monotonic() < t_end:
        slot = reader.pin(timeout=0.5)
        if slot is None:
            continue
        x = slot.tensors["payload"]
        first = float(x.sum())
        want = expected_value(slot.frame_id) * x.numel()
        time.sleep(hold_s)  # the writer laps the ring many times meanwhile
        again = float(x.sum())
        ok = first == want and again == want and bool((x == expected_value(slot.frame_id)).all())
        torn += 0 if ok else 1
        assert slot.seq > last
        last = slot.seq
        reads += 1
        reader.release(slot)
    conn.send({"reads": reads, "torn": torn, "last_seq": last, "stats": ring.stats()["readers"][name]})
    torch.set_num_threads(1)


if __name__ == "__main__":
    main(int(sys.argv[1]))
