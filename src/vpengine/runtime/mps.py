"""CUDA MPS: find, start and stop a control daemon, and decide which processes use it.

Note [MPS and ownership of device memory]
~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~
With MPS, every client process runs its kernels through one server, so several models share the GPU at the same
time instead of time-slicing. Memory a *client* allocates lives in the server's context and dies with the server.
The engine therefore keeps the parent process (which allocates the shared mailboxes) off MPS, and only the model
workers are clients: if the daemon dies, the workers crash, the supervisor restarts them, and -- since the daemon no
longer answers -- they come back without MPS, slower but serving, mapping the same mailboxes from the descriptors the
parent kept. ``stats()`` says which workers run on MPS.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

SYSTEM_PIPE_DIR = "/tmp/nvidia-mps"
CONTROL = "nvidia-cuda-mps-control"


def private_pipe_dir() -> str:
    """The owner-only pipe directory ``vpengine mps start`` uses by default."""
    base = os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()
    return str(Path(base) / f"vpengine-mps-{os.getuid()}")


def candidate_dirs(configured: str | None = None) -> list[str]:
    dirs = [configured, os.environ.get("CUDA_MPS_PIPE_DIRECTORY"), private_pipe_dir(), SYSTEM_PIPE_DIR]
    out: list[str] = []
    for d in dirs:
        if d and d not in out:
            out.append(d)
    return out


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's daemon: alive, though we may not be allowed to use it
        return True
    return True


def status(directory: str | None = None) -> dict[str, Any]:
    """Whether an MPS control daemon runs for ``directory`` (default: the first candidate directory).

    The pipe directory holds named pipes (``control``), not sockets, and they stay behind when a daemon is killed;
    the daemon's pid file and a live process with that pid are what tell a running daemon from a dead one.
    """
    d = directory or candidate_dirs()[0]
    control = Path(d) / "control"
    pidfile = Path(d) / "nvidia-cuda-mps-control.pid"
    out: dict[str, Any] = {"pipe_directory": d, "reachable": False, "reason": "", "pid": None}
    if not control.exists():
        out["reason"] = f"no control pipe at {control}"
        return out
    try:
        pid = int(pidfile.read_text().strip())
    except (OSError, ValueError):
        out["reason"] = f"no readable pid file at {pidfile}"
        return out
    out["pid"] = pid
    if not _pid_alive(pid):
        out["reason"] = f"the daemon (pid {pid}) of {d} is gone"
        return out
    out["reachable"] = True
    return out


def find_daemon(configured: str | None = None) -> str | None:
    """The pipe directory of the first reachable daemon among the candidates, or None."""
    for d in candidate_dirs(configured):
        if status(d)["reachable"]:
            return d
    return None


def _env(directory: str) -> dict[str, str]:
    env = dict(os.environ)
    env["CUDA_MPS_PIPE_DIRECTORY"] = directory
    env["CUDA_MPS_LOG_DIRECTORY"] = str(Path(directory) / "log")
    return env


def start(directory: str | None = None, timeout: float = 10.0) -> dict[str, Any]:
    """Start a control daemon with an owner-only pipe directory. Returns its status."""
    exe = shutil.which(CONTROL)
    if exe is None:
        raise RuntimeError(f"{CONTROL} is not on PATH (it ships with the NVIDIA driver / CUDA toolkit)")
    d = directory or private_pipe_dir()
    if status(d)["reachable"]:
        return {**status(d), "started": False}
    Path(d).mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(d, 0o700)
    (Path(d) / "log").mkdir(mode=0o700, exist_ok=True)
    # -d daemonises; its output goes to the log directory (no pipes: the daemon would inherit and hold them)
    proc = subprocess.run(
        [exe, "-d"],
        env=_env(d),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        timeout=timeout,
        check=False,
    )
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        st = status(d)
        if st["reachable"]:
            return {**st, "started": True}
        time.sleep(0.05)
    log_tail = ""
    for f in sorted((Path(d) / "log").glob("*.log")):
        log_tail += f"\n--- {f.name}:\n" + f.read_text(errors="replace")[-2000:]
    raise RuntimeError(
        f"MPS control daemon did not come up at {d} within {timeout} s (exit {proc.returncode}, stderr "
        f"{proc.stderr.decode(errors='replace').strip()!r}); pipe directory holds "
        f"{sorted(p.name for p in Path(d).iterdir())}{log_tail}"
    )


def stop(directory: str | None = None, timeout: float = 10.0) -> bool:
    """Ask the daemon at ``directory`` to quit. Returns whether one was running."""
    exe = shutil.which(CONTROL)
    d = directory or private_pipe_dir()
    if exe is None or not status(d)["reachable"]:
        return False
    subprocess.run([exe], input=b"quit\n", env=_env(d), check=False, capture_output=True, timeout=timeout)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and status(d)["reachable"]:
        time.sleep(0.05)
    return True


@contextlib.contextmanager
def off_mps() -> Iterator[str]:
    """Within the block, CUDA initialised in this process does not join any MPS server."""
    empty = tempfile.mkdtemp(prefix="vpengine-nomps-")
    old = os.environ.get("CUDA_MPS_PIPE_DIRECTORY")
    os.environ["CUDA_MPS_PIPE_DIRECTORY"] = empty
    try:
        yield empty
    finally:
        if old is None:
            os.environ.pop("CUDA_MPS_PIPE_DIRECTORY", None)
        else:
            os.environ["CUDA_MPS_PIPE_DIRECTORY"] = old
        shutil.rmtree(empty, ignore_errors=True)
