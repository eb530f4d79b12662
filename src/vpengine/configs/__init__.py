"""Configs that ship with the package, found by name from any directory (``-c tiny``, ``-c dinov2s_depth_seg_det``).

The repository's ``configs/`` folder is a link to this one, so ``configs/tiny.yaml`` paths keep working in a clone.
"""

from __future__ import annotations

from pathlib import Path

HERE = Path(__file__).resolve().parent
_EXTS = (".yaml", ".yml", ".json")


def names() -> list[str]:
    """The shipped configs' names, sorted."""
    return sorted(p.stem for p in HERE.iterdir() if p.suffix in _EXTS)


def describe(name: str) -> str:
    """What a shipped config is for, in one line: its leading comment's first line, cut before a colon when the
    sentence goes on to the next line. '' when it has no leading comment."""
    for line in resolve(name).read_text().splitlines():
        if line.startswith("#"):
            text = line.lstrip("#").strip()
            if not text.endswith(".") and ": " in text:
                text = text.split(": ", 1)[0]
            return text.rstrip(":")
        if line.strip():
            break
    return ""


def resolve(spec: str | Path) -> Path:
    """A config file from a path (used as it is when it exists) or the name of a shipped config (``tiny``, also
    ``tiny.yaml``). Raises FileNotFoundError naming the shipped configs when it is neither."""
    path = Path(spec)
    if path.is_file():
        return path
    stem = path.name
    for ext in _EXTS:
        stem = stem.removesuffix(ext)
    if str(spec) in (stem, path.name):  # a bare name, not a path into some folder
        for ext in _EXTS:
            if (HERE / f"{stem}{ext}").is_file():
                return HERE / f"{stem}{ext}"
    raise FileNotFoundError(
        f"config {str(spec)!r} is neither a file nor a shipped config; shipped (by name, e.g. -c tiny): "
        f"{', '.join(names())}"
    )
