"""Where ``torch.compile`` keeps what it compiled: a folder per release of everything that shapes it.

Note [Compile cache key]
~~~~~~~~~~~~~~~~~~~~~~~~
``torch.compile`` writes what it compiled to disk (dynamo's and AOTAutograd's entries, inductor's FX graphs and
generated code, Triton's kernels) and a later start reads it back instead of compiling again. torch keys those
entries on what torch sees: the traced graph, the example shapes, its config, the device, the torch / Triton / CUDA
build. It does not see all of what vpengine hands it (a custom kernel's source, a registered op's implementation),
so an entry written by one release of vpengine could be read by the next: issue 28 saw a start fail with "seg:
outputs differ from the declared output_spec" after an upgrade, until the old inductor cache was removed.

So a compile runs over caches of its own, ``<cache>/compile/<key>/inductor`` and ``.../triton`` (``<cache>``: the
``cache_dir`` of ``make_executor``, by default ``catalog.cache_dir()``), where ``<key>`` (``compile_key``) names the
vpengine release and a digest of its source files (so an edit that keeps the version number counts too), the torch
release and build, the Triton release, the Python release and the machine's architecture. Entries written under
another key are never read: ignored, never fatal, and never deleted (another release may be running from them).
The device is not in the key: torch and Triton key their entries on it themselves.

The folders are chosen through ``TORCHINDUCTOR_CACHE_DIR`` and ``TRITON_CACHE_DIR``, which torch and Triton read
when they look for an entry, not when they are imported. ``use_compile_cache`` sets them just before a compile, in
the process that compiles: a worker process (forked from the zygote, which never compiles) or the engine's own
process in thread mode, where workers build under one lock so two compiles never switch folders under each other. A
variable the user set is theirs and left as it is. One that holds inductor's default folder is not taken for the
user's: inductor itself writes its default back into the environment the first time it looks.
"""

from __future__ import annotations

import functools
import hashlib
import os
import platform
import re
import sys
from pathlib import Path

import torch

from vpengine._version import __version__

#: The variables that choose the folders, and each one's subfolder of a key's folder.
CACHE_VARIABLES = {"TORCHINDUCTOR_CACHE_DIR": "inductor", "TRITON_CACHE_DIR": "triton"}

# What use_compile_cache set in this process, so that a later call (another cache root) may replace it.
_ours: dict[str, str] = {}


def _source_digest() -> str:
    """sha256 over the package's Python files (relative path and bytes): any edit of vpengine changes it."""
    package = Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        h.update(path.relative_to(package).as_posix().encode())
        h.update(b"\0")
        h.update(path.read_bytes())
    return h.hexdigest()


def _triton_version() -> str:
    try:
        import triton
    except ImportError:
        return "none"
    return str(triton.__version__)


@functools.cache
def compile_key() -> str:
    """The name of this install's compile cache folder (Note [Compile cache key]): readable release names, then a
    digest of everything in the key."""
    parts = {
        "vpengine": __version__,
        "source": _source_digest(),
        "torch": torch.__version__,
        "torch_git": torch.version.git_version,
        "cuda": str(torch.version.cuda),
        "hip": str(torch.version.hip),
        "triton": _triton_version(),
        "python": f"{platform.python_implementation()}-{'.'.join(map(str, sys.version_info[:3]))}",
        "machine": platform.machine(),
    }
    digest = hashlib.sha256(repr(sorted(parts.items())).encode()).hexdigest()[:16]
    readable = f"vpengine-{__version__}-torch-{torch.__version__}-py{sys.version_info[0]}{sys.version_info[1]}"
    return f"{re.sub(r'[^A-Za-z0-9._-]', '_', readable)}-{digest}"


def _inductor_default() -> str | None:
    try:
        from torch._inductor.runtime.cache_dir_utils import default_cache_dir
    except ImportError:  # a torch without that module writes no default back
        return None
    return os.path.abspath(default_cache_dir())


def use_compile_cache(root: Path) -> dict[str, str]:
    """Point the compile caches of this process at ``root / compile_key()`` unless the user chose them (Note
    [Compile cache key]). Returns each variable's folder now, whoever chose it."""
    folder = root / compile_key()
    defaults = {"TORCHINDUCTOR_CACHE_DIR": _inductor_default()}
    for var, sub in CACHE_VARIABLES.items():
        now = os.environ.get(var)
        if now is None or now == _ours.get(var) or now == defaults.get(var):
            _ours[var] = os.environ[var] = str(folder / sub)
    return {var: os.environ[var] for var in CACHE_VARIABLES}
