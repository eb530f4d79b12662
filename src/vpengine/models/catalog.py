"""The checkpoint catalog: which official files the zoo uses, where they come from, and how they are verified.

Each :class:`Entry` names one file: its URL, file name, sha256, size in bytes, licence and the recipes that use it.
The shipped list is ``catalog.json`` next to this module; every sha256 and size in it was taken from a source that
is recorded in the entry (``source``). Where no source was found the digest is ``null`` and the entry says why
(``sha256_missing``): such a file is never used until the user supplies a digest (``fetch --sha256 HEX``) or accepts
the one computed on download (``fetch --trust-on-first-use``); that choice is recorded as a *pin* in the cache.

Cache layout (``weights.cache_dir()``: config ``weights.cache_dir``, $VPENGINE_CACHE, $XDG_CACHE_HOME/vpengine)::

    <cache>/weights/<name>/<file>              the verified checkpoint ("/" in a name becomes "--")
    <cache>/weights/<name>/<file>.part         an interrupted download, resumed with an HTTP Range request
    <cache>/weights/<name>/<file>.verified     size, mtime and sha256 at the last full hash (skips re-hashing)
    <cache>/weights/catalog.local.json         user pins (digests for entries without one) and custom entries

Downloads (:func:`fetch`) come only from the entry's URL, show a tqdm progress bar, resume a partial file, check
size and sha256 *before* the file is renamed into place (a mismatch deletes the partial file), and hold an exclusive
lock on the cache so two workers that need the same file never write it at once.

Tests and site setups can swap the catalog: :func:`use` (in-process) or $VPENGINE_CATALOG (JSON files merged over
the shipped catalog, inherited by worker processes).
"""

from __future__ import annotations

import contextlib
import datetime
import fcntl
import hashlib
import http.client
import json
import logging
import os
import re
import shutil
import sys
import threading
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from vpengine.models.weights import CheckpointError
from vpengine.models.weights import cache_dir as default_cache_dir

log = logging.getLogger("vpengine.weights")

#: The catalog shipped with the package.
SHIPPED = Path(__file__).with_name("catalog.json")
SCHEMA = 1
#: Environment variable: extra catalog JSON files (os.pathsep-separated), merged over the shipped one.
CATALOG_ENV = "VPENGINE_CATALOG"
LOCAL_CATALOG = "catalog.local.json"

_SHA_RE = re.compile(r"^[0-9a-f]{64}$")
# One optional "/" so that Hugging Face style names (facebook/dinov2-small) are accepted.
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*(/[A-Za-z0-9][A-Za-z0-9._-]*)?$")
_SUFFIXES = (".part", ".verified")
_REQUIRED = ("name", "url", "file", "sha256", "size", "licence", "recipes")
_OPTIONAL = ("default_for", "description", "source", "sha256_missing")
_CHUNK = 1 << 20


class CatalogError(ValueError):
    """A catalog file or entry that is malformed; the message names the entry, the field and what is accepted."""


def _check_sha256(value: Any, what: str) -> str:
    if not isinstance(value, str) or not _SHA_RE.match(value.lower()):
        raise CatalogError(f"{what}: sha256 must be 64 hexadecimal characters, got {value!r}")
    return value.lower()


@dataclass(frozen=True)
class Entry:
    """One checkpoint file of the catalog."""

    name: str
    url: str
    file: str
    #: Lower-case hex digest, or None when no trusted source publishes one (see ``sha256_missing``).
    sha256: str | None
    #: Size in bytes, or None when unknown.
    size: int | None
    licence: str
    #: Recipes that can load this file.
    recipes: tuple[str, ...] = ()
    #: Recipes for which this file is the default checkpoint.
    default_for: tuple[str, ...] = ()
    description: str = ""
    #: Where the digest and size come from.
    source: str = ""
    #: Why there is no digest (required when ``sha256`` is None).
    sha256_missing: str | None = None

    def __post_init__(self) -> None:
        where = f"catalog entry {self.name!r}"
        if not isinstance(self.name, str) or not _NAME_RE.match(self.name) or ".." in self.name:
            raise CatalogError(
                f"catalog entry name {self.name!r} must be letters, digits, '.', '_', '-' with at most one '/'"
            )
        url = urllib.parse.urlsplit(self.url) if isinstance(self.url, str) else None
        if url is None or url.scheme not in ("https", "http") or not url.netloc:
            raise CatalogError(f"{where}: url must be an http(s) URL, got {self.url!r}")
        if (
            not isinstance(self.file, str)
            or not self.file
            or self.file in (".", "..")
            or "/" in self.file
            or "\\" in self.file
            or self.file.endswith(_SUFFIXES)
        ):
            raise CatalogError(
                f"{where}: file must be a plain file name (no '/', not ending in {_SUFFIXES}), got {self.file!r}"
            )
        if self.sha256 is not None:
            object.__setattr__(self, "sha256", _check_sha256(self.sha256, where))
        elif not self.sha256_missing:
            raise CatalogError(f"{where}: sha256 is null, so sha256_missing must say why")
        if self.size is not None and (
            not isinstance(self.size, int) or isinstance(self.size, bool) or self.size <= 0
        ):
            raise CatalogError(f"{where}: size must be a positive number of bytes or null, got {self.size!r}")
        if not isinstance(self.licence, str) or not self.licence.strip():
            raise CatalogError(f"{where}: licence must be a non-empty string, got {self.licence!r}")
        for key in ("recipes", "default_for"):
            value = getattr(self, key)
            if isinstance(value, str) or not all(isinstance(r, str) and r for r in value):
                raise CatalogError(f"{where}: {key} must be a list of recipe names, got {value!r}")
            object.__setattr__(self, key, tuple(value))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "catalog") -> Entry:
        """Build an entry from its JSON form, naming the missing or unknown fields on error."""
        if not isinstance(data, Mapping):
            raise CatalogError(f"{where}: every entry must be a JSON object, got {type(data).__name__}")
        label = f"{where}: entry {data.get('name', '?')!r}"
        missing = [k for k in _REQUIRED if k not in data]
        unknown = sorted(set(data) - set(_REQUIRED) - set(_OPTIONAL))
        if missing:
            raise CatalogError(f"{label}: missing fields {missing} (required: {list(_REQUIRED)})")
        if unknown:
            raise CatalogError(f"{label}: unknown fields {unknown} (accepted: {list(_REQUIRED + _OPTIONAL)})")
        try:
            return cls(**{k: data[k] for k in _REQUIRED + _OPTIONAL if k in data})
        except CatalogError as e:
            raise CatalogError(f"{where}: {e}") from None

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {k: getattr(self, k) for k in _REQUIRED + _OPTIONAL}
        d["recipes"], d["default_for"] = list(self.recipes), list(self.default_for)
        return {k: v for k, v in d.items() if v is not None or k in _REQUIRED}

    def directory(self, cache: str | Path) -> Path:
        return Path(cache) / "weights" / self.name.replace("/", "--")

    def path(self, cache: str | Path) -> Path:
        """Where the verified file lives in ``cache`` (whether or not it is there)."""
        return self.directory(cache) / self.file


class Catalog:
    """An immutable set of entries with unique names."""

    def __init__(self, entries: Iterable[Entry] = ()) -> None:
        self._entries: dict[str, Entry] = {}
        for e in entries:
            if e.name in self._entries:
                raise CatalogError(f"catalog entry {e.name!r} appears twice")
            self._entries[e.name] = e

    @classmethod
    def from_dict(cls, data: Any, where: str = "catalog") -> Catalog:
        if not isinstance(data, Mapping) or not isinstance(data.get("entries"), list):
            raise CatalogError(f"{where}: expected a JSON object with an 'entries' list")
        if data.get("schema", SCHEMA) != SCHEMA:
            raise CatalogError(f"{where}: schema {data.get('schema')!r} is not supported (expected {SCHEMA})")
        return cls(Entry.from_dict(e, where) for e in data["entries"])

    @classmethod
    def load(cls, path: str | Path) -> Catalog:
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise CatalogError(f"catalog file {str(path)!r} does not exist") from None
        except json.JSONDecodeError as e:
            raise CatalogError(f"catalog file {str(path)!r} is not valid JSON: {e}") from None
        return cls.from_dict(data, str(path))

    def to_dict(self) -> dict[str, Any]:
        return {"schema": SCHEMA, "entries": [e.to_dict() for e in self]}

    def merged(self, other: Iterable[Entry]) -> Catalog:
        """A copy where entries of ``other`` replace same-named ones and add the rest."""
        entries = dict(self._entries)
        entries.update((e.name, e) for e in other)
        return Catalog(entries.values())

    def find(self, name: str) -> Entry | None:
        return self._entries.get(name)

    def names(self) -> list[str]:
        return list(self._entries)

    def for_recipe(self, recipe: str) -> list[Entry]:
        """Every entry a recipe can load."""
        return [e for e in self if recipe in e.recipes]

    def default_for(self, recipe: str) -> Entry | None:
        """The default checkpoint of a recipe, if the catalog names one."""
        return next((e for e in self if recipe in e.default_for), None)

    def __iter__(self) -> Iterator[Entry]:
        return iter(self._entries.values())

    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, name: object) -> bool:
        return name in self._entries


# ------------------------------------------------------------------------------------------ the active catalog
_override: Catalog | None = None
_shipped: Catalog | None = None


def shipped() -> Catalog:
    """The catalog shipped with vpengine (loaded once)."""
    global _shipped
    if _shipped is None:
        _shipped = Catalog.load(SHIPPED)
    return _shipped


def active() -> Catalog:
    """The catalog in use: the one installed by :func:`use`, else the shipped one plus $VPENGINE_CATALOG files."""
    if _override is not None:
        return _override
    cat = shipped()
    for part in filter(None, os.environ.get(CATALOG_ENV, "").split(os.pathsep)):
        extra = Catalog.load(part)
        for e in extra:
            old = cat.find(e.name)
            if old is not None and old.sha256 and e.sha256 != old.sha256:
                log.warning("%s overrides the digest of catalog entry %s (%s)", part, e.name, e.sha256)
        cat = cat.merged(extra)
    return cat


@contextlib.contextmanager
def use(catalog: Catalog) -> Iterator[Catalog]:
    """Make ``catalog`` the active one for the duration of the block (tests, embedding applications)."""
    global _override
    before, _override = _override, catalog
    try:
        yield catalog
    finally:
        _override = before


# ----------------------------------------------------------------------------- user pins and custom entries
def _weights_root(cache: str | Path) -> Path:
    return Path(cache) / "weights"


def local_catalog(cache: str | Path) -> Catalog:
    """Pins and custom entries recorded in ``cache`` by ``fetch --sha256`` / ``--trust-on-first-use`` / ``--url``."""
    path = _weights_root(cache) / LOCAL_CATALOG
    return Catalog.load(path) if path.is_file() else Catalog()


def _record_local(cache: str | Path, entry: Entry) -> None:
    """Add or replace ``entry`` in the cache's local catalog (atomic rewrite)."""
    root = _weights_root(cache)
    root.mkdir(parents=True, exist_ok=True)
    cat = local_catalog(cache).merged([entry])
    tmp = root / f".{LOCAL_CATALOG}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(cat.to_dict(), indent=2) + "\n")
    os.replace(tmp, root / LOCAL_CATALOG)


def effective(entry: Entry, cache: str | Path) -> Entry:
    """``entry`` with the user's pin applied when the catalog has no digest for it.

    A pin only fills a missing digest: a published sha256 is never replaced by a local one, and a pin recorded for
    another URL or file name (the catalog changed since) is ignored.
    """
    if entry.sha256 is not None:
        return entry
    pin = local_catalog(cache).find(entry.name)
    if pin is None or pin.sha256 is None or (pin.url, pin.file) != (entry.url, entry.file):
        return entry
    return replace(entry, sha256=pin.sha256, size=pin.size or entry.size, source=pin.source)


def find(name: str, cache: str | Path | None = None) -> Entry | None:
    """The entry called ``name``: the active catalog first, then custom entries recorded in the cache."""
    entry = active().find(name)
    if entry is not None:
        return entry
    return local_catalog(cache if cache is not None else default_cache_dir()).find(name)


def default_for(recipe: str) -> Entry | None:
    """The default checkpoint of ``recipe`` in the active catalog."""
    return active().default_for(recipe)


# ------------------------------------------------------------------------------------------- hashing, stamps
def sha256_file(path: str | Path, progress: bool = False, desc: str | None = None) -> str:
    """Hex sha256 of a file, read in 1 MiB chunks (optionally with a progress bar)."""
    path = Path(path)
    h = hashlib.sha256()
    with _bar(path.stat().st_size, 0, desc or f"hashing {path.name}", progress) as bar, path.open("rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
            bar.update(len(chunk))
    return h.hexdigest()


def _stamp_path(path: Path) -> Path:
    return path.with_name(path.name + ".verified")


def _write_stamp(path: Path, digest: str) -> None:
    st = path.stat()
    stamp = {"sha256": digest, "size": st.st_size, "mtime_ns": st.st_mtime_ns}
    # Unique per thread: in thread mode two workers can stamp the same file at once.
    tmp = path.with_name(f".{path.name}.verified.{os.getpid()}.{threading.get_ident()}.tmp")
    tmp.write_text(json.dumps(stamp) + "\n")
    os.replace(tmp, _stamp_path(path))  # atomic: a concurrent reader never sees half a stamp


def _stamp_matches(path: Path, digest: str) -> bool:
    """True if the file was fully hashed to ``digest`` and has not changed (size, mtime) since."""
    try:
        stamp = json.loads(_stamp_path(path).read_text())
        st = path.stat()
    except (OSError, ValueError):
        return False
    return stamp == {"sha256": digest, "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def _human(n: int | None) -> str:
    if n is None:
        return "unknown size"
    size = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if size < 1024 or unit == "GiB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1024
    return f"{n} B"  # pragma: no cover - unreachable


def _bar(total: int | None, initial: int, desc: str, enabled: bool) -> Any:
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


# -------------------------------------------------------------------------------------------------- locking
@contextlib.contextmanager
def _cache_lock(cache: str | Path, what: str) -> Iterator[None]:
    """Exclusive lock on the cache's weights directory while a file is being written into it.

    Why: in process mode the foundation model and a head can need the same checkpoint (depth_anything_v2_vits
    holds both the DA-V2 encoder and its depth head) and resolve it in two processes at once. The lock is an
    ``flock`` on the directory itself, so no lock file is left behind; it is released if the holder dies.
    """
    root = _weights_root(cache)
    root.mkdir(parents=True, exist_ok=True)
    fd = os.open(root, os.O_RDONLY | os.O_DIRECTORY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.warning("waiting for another vpengine process writing into %s (%s)", root, what)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


# ------------------------------------------------------------------------------------------------ download
def _user_agent() -> str:
    from vpengine import __version__

    return f"vpengine/{__version__} (checkpoint download)"


def _remove_quietly(path: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        path.unlink()


def _download(
    entry: Entry, dest: Path, expected: str | None, progress: bool, timeout: float
) -> tuple[str, int]:
    """Download ``entry.url`` to ``dest`` (through ``dest.part``, resuming it); returns (sha256, size).

    With ``expected`` set, the digest is checked before the rename and a mismatch deletes the partial file.
    The caller holds the cache lock.
    """
    part = dest.with_name(dest.name + ".part")
    dest.parent.mkdir(parents=True, exist_ok=True)
    h = hashlib.sha256()
    offset = part.stat().st_size if part.is_file() else 0
    if entry.size is not None and offset > entry.size:
        log.warning("%s: partial download %s is larger than the file; starting again", entry.name, part)
        _remove_quietly(part)
        offset = 0
    if offset:
        # Re-hash what is already there so the final digest covers the whole file without reading it twice.
        with part.open("rb") as f:
            while chunk := f.read(_CHUNK):
                h.update(chunk)
    if entry.size is not None:
        free = shutil.disk_usage(dest.parent).free
        if free < entry.size - offset:
            raise CheckpointError(
                f"not enough disk space for {entry.name}: {_human(entry.size - offset)} needed in {dest.parent}, "
                f"{_human(free)} free"
            )
    headers = {"User-Agent": _user_agent()}
    if offset and (entry.size is None or offset < entry.size):
        headers["Range"] = f"bytes={offset}-"
    written = offset
    if "Range" in headers or not offset:
        req = urllib.request.Request(entry.url, headers=headers)
        try:
            resp = urllib.request.urlopen(req, timeout=timeout)
        except urllib.error.HTTPError as e:
            if e.code == 416 and offset:  # nothing left to send: the partial file may already be complete
                resp = None
            else:
                raise CheckpointError(
                    f"download of {entry.name} from {entry.url} failed: HTTP {e.code} {e.reason}"
                ) from None
        except (urllib.error.URLError, OSError) as e:
            reason = getattr(e, "reason", e)
            raise CheckpointError(f"download of {entry.name} from {entry.url} failed: {reason}") from None
        if resp is not None:
            with resp:
                mode = "ab"
                if offset and resp.status != 206:
                    # The server ignored the Range request: start from the beginning.
                    log.warning("%s: server does not resume downloads; starting again", entry.name)
                    h, offset, written, mode = hashlib.sha256(), 0, 0, "wb"
                elif offset:
                    start = _content_range_start(resp.headers.get("Content-Range"))
                    if start != offset:
                        raise CheckpointError(
                            f"download of {entry.name}: asked to resume at byte {offset}, server answered "
                            f"{resp.headers.get('Content-Range')!r}; delete {part} and fetch again"
                        )
                length = resp.headers.get("Content-Length")
                sent = offset + int(length) if length and length.isdigit() else None
                total = entry.size or sent
                with part.open(mode) as out, _bar(total, offset, entry.name, progress) as bar:
                    error: BaseException | None = None
                    try:
                        while chunk := resp.read(_CHUNK):
                            out.write(chunk)
                            h.update(chunk)
                            written += len(chunk)
                            bar.update(len(chunk))
                    # connection reset, socket timeout, truncated chunked body
                    except (OSError, ValueError, http.client.HTTPException) as e:
                        error = e
                    out.flush()
                    os.fsync(out.fileno())
                # read(n) returns b"" when the server closes early, so a short body is detected by its length.
                if error is not None or (sent is not None and written < sent):
                    why = f" ({type(error).__name__}: {error})" if error is not None else ""
                    raise CheckpointError(
                        f"download of {entry.name} from {entry.url} was interrupted after {_human(written)} of "
                        f"{_human(total)}{why}; the partial file {part} is kept: fetch again to resume"
                    )
    digest = h.hexdigest()
    if entry.size is not None and written != entry.size:
        if written < entry.size:
            raise CheckpointError(
                f"download of {entry.name} ended early: {written} of {entry.size} bytes; the partial file "
                f"{part} is kept: fetch again to resume"
            )
        _remove_quietly(part)
        raise CheckpointError(
            f"download of {entry.name} from {entry.url} has {written} bytes, the catalog says {entry.size}; "
            "the partial file was deleted"
        )
    if expected is not None and digest != expected:
        _remove_quietly(part)
        raise CheckpointError(
            f"sha256 mismatch for {entry.name} from {entry.url}: expected {expected}, got {digest}; "
            "the downloaded file was deleted and nothing was cached"
        )
    os.replace(part, dest)  # atomic: a reader sees either no file or the verified one
    dir_fd = os.open(dest.parent, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    _write_stamp(dest, digest)
    return digest, written


def _content_range_start(value: str | None) -> int | None:
    m = re.match(r"^bytes (\d+)-\d+/(\d+|\*)$", (value or "").strip())
    return int(m.group(1)) if m else None


# ------------------------------------------------------------------------------------------------ public API
@dataclass
class FetchResult:
    """What :func:`fetch` did."""

    entry: Entry
    path: Path
    sha256: str
    downloaded: bool
    #: Set when a digest was recorded in the cache's local catalog (and how: "--sha256" or "trust-on-first-use").
    pinned: str | None = None
    notes: list[str] = field(default_factory=list)


def _unverifiable(entry: Entry) -> CheckpointError:
    return CheckpointError(
        f"checkpoint {entry.name!r} has no known sha256 ({entry.sha256_missing or 'none recorded'}), so vpengine "
        f"will not use it unverified. Run `vpengine weights fetch {entry.name} --sha256 HEX` with a digest you "
        f"trust, or `vpengine weights fetch {entry.name} --trust-on-first-use` to accept and record the digest "
        "of what is downloaded now"
    )


def fetch(
    entry: Entry,
    cache: str | Path,
    *,
    sha256: str | None = None,
    trust_on_first_use: bool = False,
    force: bool = False,
    progress: bool = True,
    timeout: float = 60.0,
) -> FetchResult:
    """Make sure the verified file of ``entry`` is in ``cache``, downloading it from ``entry.url`` if needed.

    ``sha256`` supplies the digest for an entry without one (it must agree with a published one); with
    ``trust_on_first_use`` the digest of the downloaded file is accepted. Either way the digest is recorded as a pin
    in the cache so later runs verify against it. ``force`` downloads again even if a verified copy is cached.
    """
    if sha256 is not None:
        sha256 = _check_sha256(sha256, f"--sha256 for {entry.name}")
    if trust_on_first_use and sha256 is not None:
        raise CheckpointError("give either --sha256 or --trust-on-first-use, not both")
    eff = effective(entry, cache)
    if entry.sha256 is not None:
        if trust_on_first_use:
            raise CheckpointError(
                f"{entry.name} has a published sha256 ({entry.sha256}); --trust-on-first-use is only for "
                "entries without one"
            )
        if sha256 is not None and sha256 != entry.sha256:
            raise CheckpointError(
                f"--sha256 {sha256} disagrees with the catalog's sha256 {entry.sha256} for {entry.name}"
            )
    # Trust-on-first-use deliberately ignores an earlier pin: the user asks to accept what is there now.
    expected = sha256 or (None if trust_on_first_use else eff.sha256)
    if expected is None and not trust_on_first_use:
        raise _unverifiable(entry)
    dest = entry.path(cache)
    pin_how = "--sha256" if sha256 is not None and entry.sha256 is None else None
    with _cache_lock(cache, entry.name):
        if dest.is_file() and not force:
            if expected is None:  # trust-on-first-use of a file that is already there: hash what we have
                digest = sha256_file(dest, progress, f"hashing {entry.name}")
                _write_stamp(dest, digest)
                pin_how = "trust-on-first-use"
            else:
                _check_cached(entry, dest, expected, progress)
                digest = expected
            downloaded = False
        else:
            if force and dest.is_file():
                _remove_quietly(_stamp_path(dest))
            try:
                digest, _size = _download(entry, dest, expected, progress, timeout)
            except BaseException:
                with contextlib.suppress(OSError):
                    dest.parent.rmdir()  # only succeeds when empty: a failed fetch leaves nothing behind
                raise
            downloaded = True
            if expected is None:
                pin_how = "trust-on-first-use"
        if pin_how is not None:
            today = datetime.date.today().isoformat()
            _record_local(
                cache,
                replace(
                    entry,
                    sha256=digest,
                    size=dest.stat().st_size,
                    sha256_missing=None,
                    source=f"pinned by the user with {pin_how} on {today}",
                ),
            )
    return FetchResult(entry, dest, digest, downloaded, pin_how)


def _check_cached(entry: Entry, path: Path, expected: str, progress: bool) -> None:
    """Raise unless the cached file hashes to ``expected`` (a fresh stamp saves re-hashing unchanged files)."""
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
    _write_stamp(path, digest)


def ensure(entry: Entry, cache_dir: str | Path, offline: bool, for_model: str | None = None) -> Path:
    """The verified file of ``entry`` in the cache; downloads it when missing unless ``offline``.

    Used at model load time (``weights.resolve_checkpoint``). A download is announced with what, from where, to
    where and how to prevent it; offline, the error names the exact path to place the file at and its URL.
    """
    who = f"{for_model}: " if for_model else ""
    eff = effective(entry, cache_dir)
    dest = entry.path(cache_dir)
    if offline and not dest.is_file():
        raise offline_error(entry, cache_dir, for_model)
    if eff.sha256 is None:
        raise CheckpointError(who + str(_unverifiable(entry)))
    if dest.is_file():  # complete: files only appear through an atomic rename, so no lock is needed to read
        try:
            _check_cached(eff, dest, eff.sha256, progress=False)
        except CheckpointError as e:
            raise CheckpointError(who + str(e)) from None
        return dest
    log.warning(
        "%sdownloading checkpoint %s (%s, licence %s) from %s to %s. To never download at run time, set "
        "weights.offline: true (or VPENGINE_OFFLINE=1) and fetch ahead with `vpengine weights fetch %s`",
        who,
        entry.name,
        _human(eff.size),
        entry.licence,
        entry.url,
        dest,
        entry.name,
    )
    try:
        return fetch(entry, cache_dir, progress=True).path
    except CheckpointError as e:
        raise CheckpointError(who + str(e)) from None


def offline_error(entry: Entry, cache: str | Path, for_model: str | None = None) -> CheckpointError:
    """The error for a checkpoint that is missing while downloads are off: where to put it and where to get it."""
    eff = effective(entry, cache)
    who = f"{for_model}: " if for_model else ""
    if eff.sha256 is not None:
        check = f"sha256 {eff.sha256}, {_human(eff.size)}"
    else:
        check = (
            f"no sha256 is known: afterwards pin one with `vpengine weights fetch {entry.name} --sha256 HEX`"
        )
    return CheckpointError(
        f"{who}checkpoint {entry.name!r} is not in the cache and downloads are off (offline mode). Place the "
        f"file at {entry.path(cache)} (download it from {entry.url}; {check}), or run "
        f"`vpengine weights fetch {entry.name}` where the network is reachable, or unset offline "
        "(weights.offline, VPENGINE_OFFLINE, HF_HUB_OFFLINE)"
    )


@dataclass
class VerifyResult:
    """Outcome of :func:`verify` for one entry."""

    entry: Entry
    path: Path
    #: OK, MISMATCH, MISSING, PARTIAL (only a .part file) or UNVERIFIABLE (cached, but no digest known).
    status: str
    expected: str | None = None
    actual: str | None = None

    @property
    def problem(self) -> bool:
        return self.status in ("MISMATCH", "UNVERIFIABLE", "MISSING")


def cache_status(entry: Entry, cache: str | Path) -> str:
    """``cached``, ``partial`` (an interrupted download) or ``missing``, without hashing."""
    path = entry.path(cache)
    if path.is_file():
        return "cached"
    return "partial" if path.with_name(path.name + ".part").is_file() else "missing"


def verify(entry: Entry, cache: str | Path, progress: bool = False) -> VerifyResult:
    """Re-hash the cached file of ``entry`` (always a full read; the stamp is refreshed on success)."""
    eff = effective(entry, cache)
    path = entry.path(cache)
    state = cache_status(entry, cache)
    if state != "cached":
        return VerifyResult(entry, path, state.upper(), eff.sha256)
    digest = sha256_file(path, progress, f"verifying {entry.name}")
    if eff.sha256 is None:
        return VerifyResult(entry, path, "UNVERIFIABLE", None, digest)
    if digest != eff.sha256:
        _remove_quietly(_stamp_path(path))
        return VerifyResult(entry, path, "MISMATCH", eff.sha256, digest)
    _write_stamp(path, digest)
    return VerifyResult(entry, path, "OK", eff.sha256, digest)


def add_custom(
    name: str, url: str, cache: str | Path, *, file: str | None = None, licence: str = "unknown"
) -> Entry:
    """A user entry for a URL the user gave explicitly (``fetch NAME --url URL``); fetched like any other.

    It has no digest until :func:`fetch` records one from ``--sha256`` or ``--trust-on-first-use``.
    """
    if active().find(name) is not None:
        raise CheckpointError(f"{name!r} is already a catalog entry; choose another name for a custom URL")
    file = file or Path(urllib.parse.urlsplit(url).path).name
    return Entry(
        name=name,
        url=url,
        file=file,
        sha256=None,
        size=None,
        licence=licence,
        sha256_missing="custom entry: digest supplied by the user",
        source=f"custom URL given by the user on {datetime.date.today().isoformat()}",
    )


def prefetch(cfg: Any) -> list[Path]:
    """Resolve the catalog checkpoints of every model of an engine config in this process (parent side).

    Returns the cached paths. Call it before workers are spawned so a large download happens once, with one
    progress bar, instead of inside a worker's start-up timeout. Models with an explicit file path, random weights
    or no catalog checkpoint are skipped; offline with a missing file raises the same error as the worker would.
    """
    from vpengine.models.weights import offline

    if cfg.weights.random_weights:
        return []
    cache = default_cache_dir(cfg.weights.cache_dir)
    paths = []
    for name, mcfg in [("foundation", cfg.foundation_model), *((h.name, h) for h in cfg.heads)]:
        if mcfg.checkpoint and Path(mcfg.checkpoint).expanduser().is_file():
            continue
        entry = find(mcfg.checkpoint, cache) if mcfg.checkpoint else default_for(mcfg.model)
        if entry is None:
            continue  # an unknown name fails in the worker with the full message
        paths.append(ensure(entry, cache, offline(cfg.weights.offline), for_model=name))
    return paths
