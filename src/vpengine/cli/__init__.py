"""Command-line interface: the output checks every command shares. The argument helpers it shares with bench/ are
in :mod:`vpengine.arguments`."""

from __future__ import annotations

import tempfile
from pathlib import Path


def prepare_out_dir(path: str | Path, exist_ok: bool, what: str = "--out") -> Path:
    """Create the output folder of a run before the engine starts, or fail in one line: a folder that holds files
    already (unless ``exist_ok``: same-named files are then replaced, the others stay), a file in the way, or a
    place that cannot be written."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{what} {str(out)!r} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not exist_ok:
        raise ValueError(
            f"{what} {str(out)!r} exists already and holds files; give a new folder, or add --exist-ok to write "
            f"into it (files of the same names are replaced, the others stay)"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
        _probe(out)
    except OSError as e:
        raise ValueError(f"cannot write {what} {str(out)!r}: {e.strerror or e}") from None
    return out


def prepare_out_file(path: str | Path, exist_ok: bool, what: str, replaceable: bool = True) -> Path:
    """Check that a run's output file (a video, a bag) can be made before the engine starts: it does not exist
    (unless ``exist_ok`` and ``replaceable``) and its folder can be created and written."""
    out = Path(path)
    if out.exists() and not (exist_ok and replaceable and out.is_file()):
        hint = ", or add --exist-ok to replace it" if replaceable and out.is_file() else " (never overwritten)"
        raise ValueError(f"{what} {str(out)!r} exists already; give a new name{hint}")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        _probe(out.parent)
    except OSError as e:
        raise ValueError(f"cannot write {what} {str(out)!r}: {e.strerror or e}") from None
    return out


def _probe(folder: Path) -> None:
    """Raise OSError unless a file can be created in ``folder`` (permissions alone do not tell: root, read-only
    mounts)."""
    with tempfile.TemporaryFile(dir=folder):
        pass
