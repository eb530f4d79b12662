"""Loading checkpoints: finding the verified file, reading it without executing code, applying it all or nothing.

Resolution of a model's ``checkpoint`` field (:func:`resolve_checkpoint`):

* ``weights.random_weights: true`` -> no file; random weights, announced loudly.
* an existing path -> that file.
* a catalog name (``catalog.py``) -> the file in the per-user cache, verified against its sha256 before use. Nothing
  is downloaded here: a missing file is an error that names the path to place it at and the command that fetches it
  (``vpengine weights fetch``, ``download.py``).
* null -> the recipe's default catalog name.

Which checkpoint a model loads is said in one place, :meth:`Model.needed_checkpoint`: the engine's check before any
worker starts (:func:`check_checkpoints`) and the model's own ``load_checkpoint`` (through
:func:`resolve_checkpoint`) both ask it. A model that does not say (a user head loading its own weights) is left
alone.

Verification: a cached file is hashed in full unless its ``.verified`` stamp (size, mtime and sha256 of the last full
hash) still matches; a file whose digest differs from the pin is refused. Reading: ``.safetensors`` through
safetensors; anything else through ``torch.load(weights_only=True)``, which refuses pickled code. Applying: every key
is checked against the model before a single tensor is copied, so a wrong file fails with the file name, the model
it was meant for and the mismatching keys, and nothing is half-loaded.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import pickle
import sys
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from vpengine.models import catalog
from vpengine.models.base import BuildContext, Model, ModelBuildError
from vpengine.models.catalog import Entry, human_size

log = logging.getLogger("vpengine.weights")

_RANDOM_WARNED: set[str] = set()
_CHUNK = 1 << 20
#: Names that are meant as a file, not a catalog entry, when no such file exists.
_FILE_SUFFIXES = (".pth", ".pt", ".bin", ".safetensors", ".ckpt")


class CheckpointError(ModelBuildError):
    """A checkpoint that cannot be used: missing, unverifiable, corrupt, unreadable, or for another model."""


def resolve_checkpoint(ctx: BuildContext, model: Model) -> Path | None:
    """The local file of the checkpoint ``model`` declares (:meth:`Model.needed_checkpoint`), or None for random
    weights, while planning, or when it declares none."""
    if ctx.plan_only:
        return None
    if ctx.engine.weights.random_weights:
        if ctx.name not in _RANDOM_WARNED:
            configured = getattr(ctx.cfg, "checkpoint", None)
            log.warning(
                "%s (%s): RANDOM WEIGHTS, outputs are meaningless (weights.random_weights is set%s)",
                ctx.name,
                ctx.cfg.model,
                f"; its checkpoint {str(configured)!r} is not loaded" if configured else "",
            )
            _RANDOM_WARNED.add(ctx.name)
        return None
    try:
        name = model.needed_checkpoint(ctx.cfg)
    except CheckpointError as e:
        raise CheckpointError(f"{ctx.name}: {e}") from None
    return None if name is None else locate_checkpoint(ctx.name, ctx.cfg.model, name)


def configured_or_default(cfg: Any, default: str | None) -> str:
    """``cfg.checkpoint``, else the recipe's ``default``: what a recipe that cannot run without weights returns from
    :meth:`Model.needed_checkpoint`; a CheckpointError when neither is set."""
    if cfg.checkpoint:
        return str(cfg.checkpoint)
    if default:
        return default
    raise CheckpointError(
        f"no checkpoint configured and recipe {cfg.model!r} has no default; set checkpoint to a file or catalog "
        "name, or weights.random_weights: true"
    )


def locate_checkpoint(model: str, recipe: str, name: str) -> Path:
    """The verified local file of checkpoint ``name`` (a path or a catalog name) for ``model``; a one-line
    CheckpointError starting with the model's name, naming the file and how to get it otherwise. Never downloads."""
    try:
        return _locate(recipe, name)
    except CheckpointError as e:
        raise CheckpointError(f"{model}: {e}") from None


def _locate(recipe: str, name: str) -> Path:
    path = Path(name).expanduser()
    if path.is_file():
        return path
    cache = catalog.cache_dir()
    entry = catalog.find(name, cache)  # the cache may hold the user's custom entries
    if entry is not None:
        return cached_checkpoint(entry, cache)
    if path.is_dir():
        found = sorted(p.name for p in path.iterdir() if p.suffix in _FILE_SUFFIXES)
        inside = f"; in it: {', '.join(found[:5])}{' ...' if len(found) > 5 else ''}" if found else ""
        raise CheckpointError(
            f"checkpoint {str(path.absolute())!r} is a folder: name the checkpoint file in it{inside}"
        )
    if path.suffix in _FILE_SUFFIXES or os.sep in name:
        relative = "" if path.is_absolute() else "; a relative path is taken from the current folder, not the config's"
        raise CheckpointError(
            f"checkpoint file {str(path.absolute())!r} does not exist (and {name!r} is not a catalog name{relative})"
        )
    raise CheckpointError(
        f"checkpoint {name!r} is neither an existing file nor a catalog name (`vpengine weights list` shows the "
        "catalog)"
    )


def check_checkpoints(cfg: Any, models: Mapping[str, Model]) -> None:
    """Raise one CheckpointError, a line per checkpoint, unless every model of ``models`` (name -> the model as
    planned) finds its checkpoint verified on disk. Runs in the parent before any worker starts (Engine), so a
    missing file is a few lines naming model, file and remedy rather than a traceback from every worker.

    What each model needs is what it declares (:meth:`Model.needed_checkpoint`), the same answer its
    ``load_checkpoint`` gets; a model that declares none is not checked.
    """
    if cfg.weights.random_weights:
        return
    problems: dict[str, list[str]] = {}  # message -> the models it concerns (a file shared by two: one line)
    for name, model in models.items():
        mcfg = cfg.foundation_model if name == "foundation" else cfg.head(name)
        try:
            needed = model.needed_checkpoint(mcfg)
            if needed is not None:
                _locate(mcfg.model, needed)
            elif getattr(mcfg, "checkpoint", None) and type(model).load_checkpoint is Model.load_checkpoint:
                # Nothing lost silently: a user who set a checkpoint expects it in use. A model with a
                # load_checkpoint of its own may read it there (docs/models.md), so only one without is said to
                # ignore it.
                log.warning(
                    "%s: checkpoint %r is set, but model %r loads none (it declares none in needed_checkpoint and "
                    "has no load_checkpoint of its own): it is ignored",
                    name,
                    str(mcfg.checkpoint),
                    mcfg.model,
                )
        except CheckpointError as e:
            problems.setdefault(str(e), []).append(name)
    if problems:
        lines = [f"{', '.join(names)}: {msg}" for msg, names in problems.items()]
        raise CheckpointError(
            f"{len(lines)} checkpoint(s) not available, so no worker was started (the engine downloads nothing; "
            "--random-weights or weights.random_weights: true runs without them):\n" + "\n".join(lines)
        )


def cached_checkpoint(entry: Entry, cache: str | Path, for_model: str | None = None) -> Path:
    """The verified file of ``entry`` in ``cache``; a CheckpointError if it is missing, unpinned or corrupt."""
    who = f"{for_model}: " if for_model else ""
    eff = catalog.effective(entry, cache)
    dest = entry.path(cache)
    if not dest.is_file():
        raise missing_error(entry, cache, for_model)
    if eff.sha256 is None:
        raise CheckpointError(who + str(unverifiable_error(entry)))
    try:  # files only appear through an atomic rename, so no lock is needed to read
        check_file(eff, dest, eff.sha256, progress=False)
    except CheckpointError as e:
        raise CheckpointError(who + str(e)) from None
    return dest


def place_hint(entry: Entry, cache: str | Path, sha256: str | None = None) -> str:
    """Where to put the file of ``entry`` by hand and where to get it: ``place the file at P (download it ...)``.
    ``sha256``: a digest the user gave for it (``fetch --sha256``), which the command to run next repeats."""
    eff = catalog.effective(entry, cache)
    if eff.sha256 is not None:
        check = f"sha256 {eff.sha256}, {human_size(eff.size)}"
    elif sha256 is not None:
        check = f"sha256 {sha256} as you gave it: {_pin_command(entry, cache, sha256)} then checks and records it"
    else:
        check = f"no sha256 is published: {_pin_command(entry, cache)} then records the digest of the file you placed"
    # The URL a fetch would use: with $HF_ENDPOINT set, the mirror, since huggingface.co may be out of reach
    return f"place the file at {entry.path(cache)} (download it from {catalog.shown_url(entry.source_url())}; {check})"


def _pin_command(entry: Entry, cache: str | Path | None = None, sha256: str | None = None) -> str:
    """The command that pins the digest of what is there now (Note [Trust on first use] in ``catalog.py``), or
    checks it against ``sha256``. An entry no catalog knows yet (a ``--url`` one, recorded only once fetched) is
    named with its URL again: by its name alone the command would not find it."""
    if sha256:
        flag = f" --sha256 {sha256}"
    else:
        flag = "" if catalog.first_use_refusal(entry) is None else " --trust-on-first-use"
    known = cache is None or catalog.find(entry.name, cache) is not None
    url = "" if known else f" --url {catalog.shown_url(entry.url)}"
    return f"`vpengine weights fetch {entry.name}{url}{flag}`"


def missing_error(
    entry: Entry, cache: str | Path, for_model: str | None = None, offline: bool = False
) -> CheckpointError:
    """The one-line error for a checkpoint that is not in the cache: what fetches it, or where to put it."""
    who = f"{for_model}: " if for_model else ""
    if offline:
        return CheckpointError(
            f"{who}{entry.name} is not in the cache and downloads are off (offline mode): " + place_hint(entry, cache)
        )
    return CheckpointError(
        f"{who}checkpoint {entry.name!r} is not in the cache: run `vpengine weights fetch {entry.name}` (or "
        f"`vpengine weights fetch --config CONFIG` for every checkpoint of a config), or {place_hint(entry, cache)}"
    )


def unverifiable_error(entry: Entry) -> CheckpointError:
    """The error for a file in the cache that has no digest to check it against (neither published nor pinned)."""
    return CheckpointError(
        f"checkpoint {entry.name!r} has no known sha256 ({entry.sha256_missing or 'none recorded'}), so vpengine "
        f"will not use it unverified: {_pin_command(entry)} records the digest of the file there now (trust on "
        f"first use), `vpengine weights fetch {entry.name} --sha256 HEX` checks it against one you trust"
    )


# ------------------------------------------------------------------------------------------- hashing, stamps
def byte_progress(total: int | None, initial: int, desc: str, enabled: bool) -> Any:
    """A tqdm bar over bytes on stderr (a no-op bar when not ``enabled``)."""
    from tqdm import tqdm

    return tqdm(
        total=total,
        initial=initial,
        desc=desc,
        unit="B",
        unit_scale=True,
        unit_divisor=1024,
        disable=not enabled,
        file=sys.stderr,
        dynamic_ncols=True,
        mininterval=0.5,
    )


def sha256_file(path: str | Path, progress: bool = False, desc: str | None = None) -> str:
    """Hex sha256 of a file, read in 1 MiB chunks (optionally with a progress bar)."""
    path = Path(path)
    h = hashlib.sha256()
    bar = byte_progress(path.stat().st_size, 0, desc or f"hashing {path.name}", progress)
    with bar, path.open("rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
            bar.update(len(chunk))
    return h.hexdigest()


def stamp_path(path: Path) -> Path:
    """Where the ``.verified`` stamp of a cached file lives."""
    return path.with_name(path.name + ".verified")


def write_stamp(path: Path, digest: str) -> None:
    """Record that ``path``, as it is now (size, mtime), hashed to ``digest``."""
    st = path.stat()
    stamp = {"sha256": digest, "size": st.st_size, "mtime_ns": st.st_mtime_ns}
    # Unique per thread: in thread mode two workers can stamp the same file at once.
    tmp = path.with_name(f".{path.name}.verified.{os.getpid()}.{threading.get_ident()}.tmp")
    tmp.write_text(json.dumps(stamp) + "\n")
    os.replace(tmp, stamp_path(path))  # atomic: a concurrent reader never sees half a stamp


def _stamp_matches(path: Path, digest: str) -> bool:
    """True if the file was fully hashed to ``digest`` and has not changed (size, mtime) since."""
    try:
        stamp = json.loads(stamp_path(path).read_text())
        st = path.stat()
    except (OSError, ValueError):
        return False
    return bool(stamp == {"sha256": digest, "size": st.st_size, "mtime_ns": st.st_mtime_ns})


def check_file(entry: Entry, path: Path, expected: str, progress: bool) -> None:
    """Raise unless ``path`` hashes to ``expected`` (a fresh stamp saves re-hashing an unchanged file)."""
    if _stamp_matches(path, expected):
        return
    if entry.size is not None and path.stat().st_size != entry.size:
        raise CheckpointError(
            f"cached checkpoint {path} has {path.stat().st_size} bytes, expected {entry.size} for {entry.name}; "
            f"delete it or run `vpengine weights fetch {entry.name} --force`"
        )
    digest = sha256_file(path, progress, f"verifying {entry.name}")
    if digest != expected:
        raise CheckpointError(
            f"cached checkpoint {path} does not match {entry.name}: expected sha256 {expected}, got {digest}; "
            f"delete it or run `vpengine weights fetch {entry.name} --force`"
        )
    write_stamp(path, digest)


# ------------------------------------------------------------------------------------------- reading, applying
def _read_failure(e: Exception) -> str:
    """Why a checkpoint could not be read, in a line. torch.load's refusal under ``weights_only`` is a page that
    suggests loading with ``weights_only=False``, which vpengine never does (it would run the file's code): kept
    is its reason, and the fix that fits."""
    text = str(e)
    if isinstance(e, pickle.UnpicklingError) or "weights_only" in text:
        reason = text.partition("WeightsUnpickler error:")[2].partition("Check the documentation")[0]
        reason = " ".join(reason.split()) or type(e).__name__
        return (
            f"not a file of tensors that loads without running code ({reason}). vpengine reads checkpoints with "
            "torch.load(weights_only=True) or safetensors: if it holds a whole pickled model or other objects, "
            "save its state_dict (torch.save(model.state_dict(), path)); otherwise the file is damaged or not a "
            "checkpoint"
        )
    return f"{type(e).__name__}: {' '.join(text.split())}"


def read_state_dict(path: str | Path) -> dict[str, torch.Tensor]:
    """Tensors from a checkpoint file, without executing any code. Unwraps {'state_dict'|'model': ...}."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            sd: Any = load_file(str(path), device="cpu")
        else:
            sd = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as e:  # truncated, corrupt, or pickled code refused by weights_only
        raise CheckpointError(f"cannot read checkpoint {str(path)!r}: {_read_failure(e)}") from None
    for key in ("state_dict", "model", "module"):
        if isinstance(sd, Mapping) and key in sd and isinstance(sd[key], Mapping):
            sd = sd[key]
    if not isinstance(sd, Mapping) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise CheckpointError(f"checkpoint {str(path)!r} does not hold a state dict of tensors")
    return dict(sd)


def _preview(keys: list[str], n: int = 8) -> str:
    return ", ".join(keys[:n]) + (f", ... ({len(keys)} in all)" if len(keys) > n else "")


def apply_state_dict(
    module: nn.Module,
    sd: Mapping[str, torch.Tensor],
    source: str,
    expected: str,
    ignore: tuple[str, ...] = (),
) -> None:
    """Load ``sd`` into ``module`` strictly, checking every key and shape first (nothing is half-loaded).

    ``source`` names the file and ``expected`` the model it should be for; both appear in the error.
    ``ignore`` lists key prefixes of the checkpoint that are not part of this module (skipped silently).
    """
    own = module.state_dict()
    theirs = {k: v for k, v in sd.items() if not k.startswith(ignore)} if ignore else dict(sd)
    missing = sorted(set(own) - set(theirs))
    unexpected = sorted(set(theirs) - set(own))
    shapes = sorted(
        f"{k}: checkpoint {tuple(theirs[k].shape)} vs model {tuple(own[k].shape)}"
        for k in set(own) & set(theirs)
        if tuple(own[k].shape) != tuple(theirs[k].shape)
    )
    if missing or unexpected or shapes:
        parts = []
        if missing:
            parts.append(f"missing keys: {_preview(missing)}")
        if unexpected:
            parts.append(f"unexpected keys: {_preview(unexpected)}")
        if shapes:
            parts.append(f"shape mismatches: {_preview(shapes, 4)}")
        raise CheckpointError(f"checkpoint {source!r} does not fit {expected}: " + "; ".join(parts))
    module.load_state_dict(theirs, strict=True)
