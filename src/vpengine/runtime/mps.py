"""CUDA MPS detection: is a control daemon reachable from this process?"""

from __future__ import annotations

import os
import socket
from pathlib import Path
from typing import Any

DEFAULT_PIPE_DIR = "/tmp/nvidia-mps"


def pipe_dir() -> str:
    return os.environ.get("CUDA_MPS_PIPE_DIRECTORY", DEFAULT_PIPE_DIR)


def status(directory: str | None = None) -> dict[str, Any]:
    """Whether an MPS control daemon answers at ``directory`` (default: $CUDA_MPS_PIPE_DIRECTORY or /tmp/nvidia-mps).

    Clients find the daemon through the ``control`` socket in the pipe directory; we check it exists and accepts a
    connection, which is what a CUDA client would do first.
    """
    d = directory or pipe_dir()
    control = Path(d) / "control"
    out: dict[str, Any] = {"pipe_directory": d, "reachable": False, "reason": ""}
    if not control.exists():
        out["reason"] = f"no control socket at {control}"
        return out
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(1.0)
    try:
        s.connect(str(control))
        out["reachable"] = True
    except OSError as e:
        out["reason"] = f"control socket at {control} does not answer: {e}"
    finally:
        s.close()
    return out
