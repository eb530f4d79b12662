"""Entry point of a worker process (see Note [Child lifecycle] in process.py for how it is started)."""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import signal
import threading
import time
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from vpengine.runtime.control import ControlBlock
    from vpengine.runtime.worker import WorkerCore

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
        specs, log_level, log_file = (init.spec, *init.more), init.log_level, init.log_file
    except (EOFError, OSError):
        os._exit(2)
    names = "+".join(s.name for s in specs)
    # its stderr shows what the parent's terminal shows (a CLI run without -v: warnings), logging.file what the
    # config asks; the handler's own level keeps the file's lower level off the terminal
    logging.basicConfig(level=init.terminal_level, format=f"%(asctime)s %(levelname)s [{names}] %(name)s: %(message)s")
    for handler in logging.getLogger().handlers:
        handler.setLevel(init.terminal_level)

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
        conn.send(Failed(describe_exception(specs[0].name, e)))
        os._exit(3)
    threading.Thread(target=watch_parent, name="parent-watch", daemon=True).start()
    building = specs[0].name
    cores: list[WorkerCore] = []
    try:
        if log_file:
            log_to_file(log_file, log_level, names)
        # a mailbox two models of this process share (the features between the backbone and a head) is mapped once:
        # opening a region consumes (closes) its descriptor
        rings: dict[str, SlotRing] = {}
        for spec in specs:
            for desc in (spec.in_ring, spec.out_ring):
                if desc.name not in rings:
                    rings[desc.name] = SlotRing.attach(desc, fds)
        assert specs[0].control is not None  # the runner gives every child spec its control block
        control = ControlBlock.attach(specs[0].control, fds)
        device = specs[0].engine_config().device
        if device.startswith("cuda"):  # the context is ours: Note [Thread stack] in gpu.py
            from vpengine.runtime.gpu import trim_thread_stack

            trim_thread_stack(int(device.partition(":")[2] or 0))
        for spec in specs:
            building = spec.name
            ring_in, ring_out = rings[spec.in_ring.name], rings[spec.out_ring.name]
            cores.append(prepare_worker(spec, ring_in, ring_out, control, True, alone=len(specs) == 1))
        if len(cores) > 1:  # one pool a process: the largest any of its models asks for
            import torch

            torch.set_num_threads(max(c.spec.engine_config().model(c.spec.name).cpu_threads for c in cores))
    except BaseException as e:
        try:
            conn.send(Failed(describe_exception(building, e)))
        finally:
            os._exit(3)
    for core in cores:  # the first was built before the others: its last sign of life is not older than READY
        control.heartbeat(core.spec.name)
    conn.send(Ready(os.getpid()))
    if len(cores) == 1:
        _serve(cores[0], conn, control, stop)  # on this thread, as ever
    ended = threading.Event()
    threads = [
        threading.Thread(target=_serve, args=(core, conn, control, stop, ended), name=f"vpengine-{core.spec.name}")
        for core in cores
    ]
    for t in threads:
        t.daemon = True
        t.start()
    ended.wait()  # a loop left: told to stop (the others are leaving too: let them finish their run), or not
    deadline = time.monotonic() + 5.0
    for t in threads:
        t.join(max(0.0, deadline - time.monotonic()))
    os._exit(0)


_send_lock = threading.Lock()  # the process's models share its socket


def _serve(
    core: WorkerCore,
    conn: Connection,
    control: ControlBlock,
    stop: threading.Event,
    ended: threading.Event | None = None,
) -> None:
    """Run one model's loop until stop; a loop that raises reports its error and ends the process (Note [Process
    groups] in process.py: the process is the unit of restart). ``ended``: set when the loop ends, for the thread
    waiting on the process's models; without it the process ends here."""
    from vpengine.runtime.sockets import Failed
    from vpengine.runtime.worker import describe_exception

    name = core.spec.name
    try:
        core.run(lambda: stop.is_set() or control.stopping)
    except BaseException as e:
        text = describe_exception(name, e)
        control.add(name, "errors")
        control.set_error(name, text)
        with _send_lock, contextlib.suppress(OSError):
            conn.send(Failed(text))
        os._exit(1)
    if ended is None:
        os._exit(0)
    ended.set()
