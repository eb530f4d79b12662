"""The checkpoint catalog: which official files the zoo uses, where to get them, and the digests that verify them.

Each :class:`Entry` names one file: its URL, file name, sha256, size in bytes, licence and the recipes that use it.
The shipped list is ``catalog.json`` next to this module; every sha256 and size in it was taken from a source that
is recorded in the entry (``source``). Where no source was found the digest is ``null`` and the entry says why
(``sha256_missing``): such a file is never used before it has a *pin* in the cache, the digest recorded by its first
``fetch`` (trust on first use, announced in one line) or given by the user (``fetch --sha256 HEX``).

An entry whose URL is a top-level file of a Hugging Face Hub repository
(``https://huggingface.co/<org>/<repo>/resolve/<revision>/<file>``) is fetched through ``huggingface_hub``
(:attr:`Entry.hub`); any other URL over plain HTTP(S). ``download.py`` fetches, ``weights.py`` loads.

Cache layout (:func:`cache_dir`: $VPENGINE_CACHE, else $XDG_CACHE_HOME/vpengine)::

    <cache>/weights/<name>/<file>              the checkpoint ("/" in a name becomes "--")
    <cache>/weights/<name>/<file>.part         an interrupted plain-HTTP download, resumed with a Range request
    <cache>/weights/<name>/<file>.verified     size, mtime and sha256 at the last full hash (skips re-hashing)
    <cache>/weights/<name>/.cache/huggingface  huggingface_hub's record of a file it fetched (commit, etag)
    <cache>/weights/catalog.local.json         user pins (digests for entries without one) and custom entries

Tests and site setups can swap the catalog: :func:`use` (in-process) or $VPENGINE_CATALOG (JSON files merged over
the shipped catalog, inherited by worker processes).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import os
import re
import urllib.parse
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

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
_HUB_PATH_RE = re.compile(r"^/([^/]+/[^/]+)/resolve/([^/]+)/([^/]+)$")
_SUFFIXES = (".part", ".verified")
_REQUIRED = ("name", "url", "file", "sha256", "size", "licence", "recipes")
_OPTIONAL = ("default_for", "description", "source", "sha256_missing")


class CatalogError(ValueError):
    """A catalog file or entry that is malformed; the message names the entry, the field and what is accepted."""


def parse_sha256(value: Any, what: str) -> str:
    """``value`` as a lower-case hex sha256; a CatalogError naming ``what`` if it is not one."""
    if not isinstance(value, str) or not _SHA_RE.match(value.lower()):
        raise CatalogError(f"{what}: sha256 must be 64 hexadecimal characters, got {value!r}")
    return value.lower()


@dataclass(frozen=True)
class HubFile:
    """A file at the top of a Hugging Face Hub model repository, at a revision (branch, tag or commit)."""

    repo_id: str
    revision: str
    filename: str


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
            or self.file in (".", "..", ".cache")  # .cache: huggingface_hub's record in the entry's directory
            or "/" in self.file
            or "\\" in self.file
            or self.file.endswith(_SUFFIXES)
        ):
            raise CatalogError(
                f"{where}: file must be a plain file name (no '/', not ending in {_SUFFIXES}), got {self.file!r}"
            )
        if self.sha256 is not None:
            object.__setattr__(self, "sha256", parse_sha256(self.sha256, where))
        elif not self.sha256_missing:
            raise CatalogError(f"{where}: sha256 is null, so sha256_missing must say why")
        if self.size is not None and (not isinstance(self.size, int) or isinstance(self.size, bool) or self.size <= 0):
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

    @property
    def hub(self) -> HubFile | None:
        """The Hub file the URL resolves, if it is ``https://huggingface.co/<org>/<repo>/resolve/<rev>/<file>``.

        Only those go through ``huggingface_hub`` (and so honour $HF_ENDPOINT, $HF_TOKEN and its login); any other
        URL, on huggingface.co or not, is fetched over plain HTTP(S).
        """
        url = urllib.parse.urlsplit(self.url)
        m = _HUB_PATH_RE.match(url.path)
        if url.scheme != "https" or url.netloc != "huggingface.co" or url.query or m is None:
            return None
        return HubFile(m[1], urllib.parse.unquote(m[2]), urllib.parse.unquote(m[3]))

    def source_url(self) -> str:
        """The URL a fetch asks now: a Hub file's place under the endpoint in force (:func:`hub_endpoint`), else
        ``url``."""
        if self.hub is None:
            return self.url
        return hub_endpoint() + urllib.parse.urlsplit(self.url).path

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


def hub_endpoint() -> str:
    """The Hugging Face Hub in force: $HF_ENDPOINT (a mirror), else https://huggingface.co.

    Read at every call, like huggingface_hub's own downloads here, so a mirror set after import still counts.
    """
    return (os.environ.get("HF_ENDPOINT") or "https://huggingface.co").rstrip("/")


def url_host(url: str) -> str:
    """``host[:port]`` of ``url``, for messages: never the ``user:token@`` a URL may carry."""
    parts = urllib.parse.urlsplit(url)
    host = parts.hostname or ""
    if ":" in host:
        host = f"[{host}]"  # IPv6
    try:
        port = parts.port
    except ValueError:  # a malformed port: leave it out rather than fail while reporting another failure
        port = None
    return f"{host}:{port}" if port is not None else host


def shown_url(url: str) -> str:
    """``url`` for messages and listings: without the ``user:token@`` of a login (a custom --url or $HF_ENDPOINT may
    carry one) and with secret query values masked (a signed link's ``?token=``; Note [Redacting] in redact.py)."""
    from vpengine.redact import redact

    parts = urllib.parse.urlsplit(url)
    if "@" in parts.netloc:
        url = urllib.parse.urlunsplit(parts._replace(netloc=url_host(url)))
    return redact(url)


def first_use_refusal(entry: Entry) -> str | None:
    """Why ``entry``, which has no digest, is not trusted on first use without the user's word; None when it is.

    Note [Trust on first use]: a fetch may record the digest of what arrives only for an entry whose URL was reviewed
    with the code, i.e. as it stands in the shipped catalog (or the one a program installs with :func:`use`), and
    only when the file comes over HTTPS (for a Hub file: from the endpoint in force). A $VPENGINE_CATALOG file's or a
    custom --url entry was never reviewed, and plain HTTP can be altered on the way; those need ``--sha256`` or
    ``--trust-on-first-use``.
    """
    reviewed = (_override if _override is not None else shipped()).find(entry.name)
    if reviewed is None or (reviewed.url, reviewed.file) != (entry.url, entry.file):
        if active().find(entry.name) is None:
            return "it is a custom --url entry"
        return f"its entry comes from ${CATALOG_ENV}, not from the catalog vpengine ships"
    source = entry.source_url()
    if urllib.parse.urlsplit(source).scheme != "https":
        return f"it would come over plain HTTP ({shown_url(source)})"
    return None


# ----------------------------------------------------------------------------- the cache, user pins, custom entries
def cache_dir() -> Path:
    """The checkpoint cache: $VPENGINE_CACHE, else $XDG_CACHE_HOME/vpengine (the one way to choose it)."""
    if os.environ.get("VPENGINE_CACHE"):
        return Path(os.environ["VPENGINE_CACHE"]).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg).expanduser() / "vpengine"


def weights_root(cache: str | Path) -> Path:
    """The folder of ``cache`` that holds every entry's directory and the local catalog."""
    return Path(cache) / "weights"


def local_catalog(cache: str | Path) -> Catalog:
    """Pins and custom entries recorded in ``cache`` by ``fetch --sha256`` / ``--trust-on-first-use`` / ``--url``."""
    path = weights_root(cache) / LOCAL_CATALOG
    return Catalog.load(path) if path.is_file() else Catalog()


def record_local(cache: str | Path, entry: Entry) -> None:
    """Add or replace ``entry`` in the cache's local catalog (atomic rewrite)."""
    root = weights_root(cache)
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
    return local_catalog(cache if cache is not None else cache_dir()).find(name)


def default_for(recipe: str) -> Entry | None:
    """The default checkpoint of ``recipe`` in the active catalog."""
    return active().default_for(recipe)


def custom_entry(name: str, url: str, *, file: str | None = None, licence: str = "unknown") -> Entry:
    """An entry for a URL the user gave explicitly (``fetch NAME --url URL``), fetched like any other.

    It has no digest until ``download.fetch`` records one from ``--sha256`` or ``--trust-on-first-use``.
    """
    if active().find(name) is not None:
        raise CatalogError(f"{name!r} is already a catalog entry; choose another name for a custom URL")
    return Entry(
        name=name,
        url=url,
        file=file or Path(urllib.parse.urlsplit(url).path).name,
        sha256=None,
        size=None,
        licence=licence,
        sha256_missing="custom entry: digest supplied by the user",
        source=f"custom URL given by the user on {datetime.date.today().isoformat()}",
    )


def human_size(n: int | None) -> str:
    """``n`` bytes for people: 84.2 MiB."""
    if n is None:
        return "unknown size"
    size = float(n)
    for unit in ("B", "KiB", "MiB", "GiB"):
        if size < 1024 or unit == "GiB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1024
    return f"{n} B"  # pragma: no cover - unreachable
