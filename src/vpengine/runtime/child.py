"""Entry point of a worker process: ``python -m vpengine.runtime.child FD`` (see Note [Child lifecycle])."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
from multiprocessing.connection import Connection


def main(fd: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C belongs to the parent, which stops us in order
    conn = Connection(fd)
    try:
        _kind, sys_path, spec, log_level = conn.recv()
    except (EOFError, OSError):
        os._exit(2)
    for p in reversed(sys_path):  # user heads by import path resolve as in the parent
        if p not in sys.path:
            sys.path.insert(0, p)
    logging.basicConfig(
        level=log_level, format=f"%(asctime)s %(levelname)s [{spec.name}] %(name)s: %(message)s"
    )

    from vpengine.runtime.control import ControlBlock
    from vpengine.runtime.process import recv_fds
    from vpengine.runtime.worker import describe_exception, prepare_worker
    from vpengine.transport.ring import SlotRing

    stop = threading.Event()

    def watch_parent() -> None:
        try:
            while True:
                if conn.recv() == ("stop",):
                    stop.set()
        except (EOFError, OSError):
            pass
        if not stop.is_set():  # the parent vanished without asking us to stop: nothing left to serve
            os._exit(0)

    try:
        fds = recv_fds(conn)
    except BaseException as e:
        conn.send(("error", describe_exception(spec.name, e)))
        os._exit(3)
    threading.Thread(target=watch_parent, name="parent-watch", daemon=True).start()
    try:
        in_ring = SlotRing.attach(spec.in_ring, fds)
        out_ring = SlotRing.attach(spec.out_ring, fds)
        control = ControlBlock.attach(spec.control, fds)  # opening a region consumes (closes) its descriptor
        core = prepare_worker(spec, in_ring, out_ring, control, own_process=True)
    except BaseException as e:
        try:
            conn.send(("error", describe_exception(spec.name, e)))
        finally:
            os._exit(3)
    conn.send(("ready", {"pid": os.getpid()}))
    try:
        core.run(lambda: stop.is_set() or control.stopping)
    except BaseException as e:
        text = describe_exception(spec.name, e)
        control.add(spec.name, "errors")
        control.set_error(spec.name, text)
        with contextlib.suppress(OSError):
            conn.send(("error", text))
        os._exit(1)
    os._exit(0)


if __name__ == "__main__":
    main(int(sys.argv[1]))
