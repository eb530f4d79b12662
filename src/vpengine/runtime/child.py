"""Entry point of a worker process (see Note [Child lifecycle] in process.py for how it is started)."""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import threading
from multiprocessing.connection import Connection

_PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int) -> None:
    """Have the kernel SIGKILL us when our parent (``parent_pid``: the zygote, or for the zygote the engine) dies
    (Note [Child lifecycle]), however we are doing then: stopped, or hung in C code that holds the GIL. Plain libc through ctypes, not vpengine.transport.linux, whose
    package imports torch: this runs before anything slow."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent_pid:  # the parent died before the request: no signal will come
        os._exit(0)


def main(fd: int, parent_pid: int) -> None:
    die_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C belongs to the parent, which stops us in order
    conn = Connection(fd)
    try:
        from vpengine.runtime.sockets import Init

        init = conn.recv()
        assert isinstance(init, Init), init
        spec, log_level, log_file = init.spec, init.log_level, init.log_file
    except (EOFError, OSError):
        os._exit(2)
    logging.basicConfig(level=log_level, format=f"%(asctime)s %(levelname)s [{spec.name}] %(name)s: %(message)s")

    from vpengine.runtime.control import ControlBlock
    from vpengine.runtime.prepare import prepare_worker
    from vpengine.runtime.sockets import Failed, Ready, Stop, recv_fds
    from vpengine.runtime.supervisor import log_to_file
    from vpengine.runtime.worker import describe_exception
    from vpengine.transport.ring import SlotRing

    stop = threading.Event()

    def watch_parent() -> None:
        try:
            while True:
                if isinstance(conn.recv(), Stop):
                    stop.set()
        except (EOFError, OSError):
            pass
        if not stop.is_set():  # the parent vanished without asking us to stop: nothing left to serve
            os._exit(0)

    try:
        fds = recv_fds(conn)
    except BaseException as e:
        conn.send(Failed(describe_exception(spec.name, e)))
        os._exit(3)
    threading.Thread(target=watch_parent, name="parent-watch", daemon=True).start()
    try:
        if log_file:
            log_to_file(log_file, log_level, spec.name)
        in_ring = SlotRing.attach(spec.in_ring, fds)
        out_ring = SlotRing.attach(spec.out_ring, fds)
        assert spec.control is not None  # the runner gives every child spec its control block
        control = ControlBlock.attach(spec.control, fds)  # opening a region consumes (closes) its descriptor
        device = spec.engine_config().device
        if device.startswith("cuda"):  # the context is ours: Note [Thread stack] in gpu.py
            from vpengine.runtime.gpu import trim_thread_stack

            trim_thread_stack(int(device.partition(":")[2] or 0))
        core = prepare_worker(spec, in_ring, out_ring, control, own_process=True)
    except BaseException as e:
        try:
            conn.send(Failed(describe_exception(spec.name, e)))
        finally:
            os._exit(3)
    conn.send(Ready(os.getpid()))
    try:
        core.run(lambda: stop.is_set() or control.stopping)
    except BaseException as e:
        text = describe_exception(spec.name, e)
        control.add(spec.name, "errors")
        control.set_error(spec.name, text)
        with contextlib.suppress(OSError):
            conn.send(Failed(text))
        os._exit(1)
    os._exit(0)
