"""Fetching checkpoints into the cache, only when asked: ``vpengine weights fetch`` or :func:`prefetch`.

Two ways in, one check at the end:

* A file on the Hugging Face Hub (:attr:`catalog.Entry.hub`) comes through ``huggingface_hub`` into the entry's
  directory (its ``local_dir`` mode): the Hub's login and $HF_TOKEN for gated repositories, $HF_ENDPOINT for mirrors,
  retries that resume an interrupted transfer, its progress bars and size checks, and a copy instead of a download
  when the file is already in the user's Hugging Face cache.
* Any other URL comes over plain HTTP(S) into ``<file>.part``; a later fetch resumes a partial file with a Range
  request.

Either way the file's size and sha256 are checked against the catalog (or the user's pin) before it counts as
cached: a mismatch deletes it and nothing is cached. An exclusive lock on the cache keeps two processes from
writing the same file at once. The engine itself never downloads (``weights.resolve_checkpoint``).
"""

from __future__ import annotations

import contextlib
import datetime
import fcntl
import http.client
import logging
import os
import shutil
import threading
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from vpengine.models import catalog
from vpengine.models.catalog import Entry, HubFile, human_size, parse_sha256
from vpengine.models.weights import (
    CheckpointError,
    byte_progress,
    check_file,
    missing_error,
    place_hint,
    sha256_file,
    stamp_path,
    write_stamp,
)

log = logging.getLogger("vpengine.weights")

_CHUNK = 1 << 20


def offline(configured: bool = False) -> bool:
    """Offline if the config says so or $VPENGINE_OFFLINE / $HF_HUB_OFFLINE is set to a true value."""
    env = any(os.environ.get(v, "").lower() in ("1", "true", "yes") for v in ("VPENGINE_OFFLINE", "HF_HUB_OFFLINE"))
    return configured or env


class Unreachable(CheckpointError):
    """The server of a file did not answer (no network, DNS, refused, timeout); ``host`` names it."""

    def __init__(self, host: str, why: object, hint: str = "") -> None:
        super().__init__(f"{host} is unreachable ({why})" + (f": {hint}" if hint else ""))
        self.host = host
        self.why = why


def source_host(entry: Entry) -> str:
    """The ``host[:port]`` a fetch of ``entry`` talks to: the Hub's endpoint ($HF_ENDPOINT) for a Hub file, else the
    URL's (never a login the URL carries)."""
    return catalog.url_host(entry.source_url())


@dataclass
class FetchResult:
    """What :func:`fetch` did."""

    entry: Entry
    path: Path
    sha256: str
    downloaded: bool
    #: Set when a digest was recorded in the cache's local catalog (and how: "--sha256" or "trust-on-first-use").
    pinned: str | None = None


def trust_notice(res: FetchResult, cache: str | Path) -> str:
    """The one line that says a digest was trusted on first use, what it is, and where it is recorded."""
    return (
        f"{res.entry.name}: no published sha256, trusted on first use: sha256 {res.sha256} is now recorded in "
        f"{catalog.weights_root(cache) / catalog.LOCAL_CATALOG} and every later use is checked against it"
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
    """Make sure the verified file of ``entry`` is in ``cache``, downloading it if needed.

    An entry of the shipped catalog without a published digest, served over HTTPS, is trusted on first use: the
    digest of the file fetched (or found) now is recorded as a pin in the cache, every later use is checked against
    it, and the result says so (``pinned``). Any other entry without a digest (a custom ``--url``, a
    $VPENGINE_CATALOG entry, a plain-HTTP source; Note [Trust on first use] in ``catalog.py``) needs the user's word
    instead: ``sha256`` (a digest to check against; it must agree with a published one) or ``trust_on_first_use``,
    which also replaces an earlier pin by the digest of what is there now. ``force`` downloads again even if a
    verified copy is cached.
    """
    if sha256 is not None:
        sha256 = parse_sha256(sha256, f"--sha256 for {entry.name}")
    if trust_on_first_use and sha256 is not None:
        raise CheckpointError("give either --sha256 or --trust-on-first-use, not both")
    eff = catalog.effective(entry, cache)
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
        why = catalog.first_use_refusal(entry)
        if why is not None:
            raise CheckpointError(
                f"{entry.name} has no known sha256 and {why}, so it is not trusted on first use: give "
                f"`--sha256 HEX` (a digest you trust) or `--trust-on-first-use` (record the digest of what arrives)"
            )
        trust_on_first_use = True
    dest = entry.path(cache)
    pin_how = "--sha256" if sha256 is not None and entry.sha256 is None else None
    with _cache_lock(cache, entry.name):
        if dest.is_file() and not force:
            if expected is None:  # trust-on-first-use of a file that is already there: hash what we have
                digest = sha256_file(dest, progress, f"hashing {entry.name}")
                write_stamp(dest, digest)
                pin_how = "trust-on-first-use"
            else:
                check_file(entry, dest, expected, progress)
                digest = expected
            downloaded = False
        else:
            if dest.is_file():
                _remove_quietly(stamp_path(dest))
            try:
                digest = _download(entry, dest, expected, progress, timeout, force)
            except BaseException as e:
                if not dest.is_file() and entry.hub is not None:
                    shutil.rmtree(dest.parent / ".cache", ignore_errors=True)  # huggingface_hub's locks, records
                with contextlib.suppress(OSError):
                    dest.parent.rmdir()  # only succeeds when empty: a failed fetch leaves nothing behind
                if isinstance(e, Unreachable):
                    raise Unreachable(e.host, e.why, place_hint(entry, cache, sha256)) from None
                raise
            downloaded = True
            if expected is None:
                pin_how = "trust-on-first-use"
        if pin_how is not None:
            today = datetime.date.today().isoformat()
            catalog.record_local(
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


def _download(entry: Entry, dest: Path, expected: str | None, progress: bool, timeout: float, force: bool) -> str:
    """Fetch ``entry`` to ``dest`` and return its sha256; a file of the wrong size or digest is deleted.

    The caller holds the cache lock.
    """
    dest.parent.mkdir(parents=True, exist_ok=True)
    hub = entry.hub
    if hub is not None:
        got = _from_hub(entry, hub, dest, progress, timeout, force)
    else:
        got = _from_url(entry, dest, progress, timeout)
    size = got.stat().st_size
    if entry.size is not None and size != entry.size:
        _discard(got, hub)
        raise CheckpointError(
            f"download of {entry.name} from {catalog.shown_url(entry.url)} has {size} bytes, the catalog says {entry.size}; "
            "the downloaded file was deleted"
        )
    digest = sha256_file(got, progress, f"verifying {entry.name}")
    if expected is not None and digest != expected:
        _discard(got, hub)
        raise CheckpointError(
            f"sha256 mismatch for {entry.name} from {catalog.shown_url(entry.url)}: expected {expected}, got {digest}; "
            "the downloaded file was deleted and nothing was cached"
        )
    if got != dest:
        os.replace(got, dest)  # atomic: a reader sees either no file or the verified one
    dir_fd = os.open(dest.parent, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    write_stamp(dest, digest)
    return digest


def _discard(path: Path, hub: HubFile | None) -> None:
    """Delete a download that failed its check, and huggingface_hub's record of it."""
    _remove_quietly(path)
    if hub is not None:
        shutil.rmtree(path.parent / ".cache", ignore_errors=True)


#: Seconds without an answer after which a request says it is still waiting (Note [A server that says nothing])
SLOW_ANSWER_S = 10.0


@contextlib.contextmanager
def _said_if_slow(name: str, url: str, timeout: float) -> Iterator[None]:
    """Note [A server that says nothing]
    ~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~
    A server (a mirror, a proxy) can take the connection and then send nothing; the request then waits for the whole
    timeout (60 s by default) before it fails, and meanwhile nothing on the terminal moves. So a request for the answer's
    headers that has not had one after SLOW_ANSWER_S says once that it is waiting, for whom and for how long at most.
    Only the wait for the headers: once a body flows, its progress bar moves, and a body that stalls fails at the
    next read's timeout."""
    if timeout <= SLOW_ANSWER_S:
        yield
        return
    timer = threading.Timer(
        SLOW_ANSWER_S,
        lambda: log.warning(
            "%s: %s has not answered for %g s; waiting up to %g s for it (the timeout; `weights fetch --timeout`)",
            name,
            catalog.url_host(url),
            SLOW_ANSWER_S,
            timeout,
        ),
    )
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()


def _from_hub(entry: Entry, hub: HubFile, dest: Path, progress: bool, timeout: float, force: bool) -> Path:
    """Fetch a Hub file into ``dest``'s directory through huggingface_hub; returns where it landed."""
    from huggingface_hub import get_hf_file_metadata, hf_hub_download, hf_hub_url
    from huggingface_hub.utils import HfHubHTTPError

    from vpengine._version import __version__

    # read when called, not when huggingface_hub was imported, so a mirror set later still counts
    endpoint = os.environ.get("HF_ENDPOINT") or None
    url = hf_hub_url(hub.repo_id, hub.filename, revision=hub.revision, endpoint=endpoint)
    # Why a probe first: with no network, hf_hub_download retries five times over half a minute and logs every try
    # (twice, through its handler and ours); one request without retries says at once whether the Hub answers.
    try:
        with _said_if_slow(entry.name, url, timeout):
            get_hf_file_metadata(url, timeout=timeout, library_name="vpengine", library_version=__version__)
    except HfHubHTTPError:
        pass  # the Hub answered (not found, gated, ...): hf_hub_download below says what, in its words
    except Exception as e:  # DNS, refused, TLS, timeout: whatever the HTTP client of this version raises
        raise Unreachable(catalog.url_host(url), e) from None
    try:
        with _hub_progress(progress), _quiet_hub_log():
            got = hf_hub_download(
                hub.repo_id,
                hub.filename,
                revision=hub.revision,
                local_dir=dest.parent,
                force_download=force,
                etag_timeout=timeout,
                endpoint=endpoint,
                library_name="vpengine",
                library_version=__version__,
            )
    # The client raises many types (HTTP status, network, consistency, offline); each message says what failed.
    except Exception as e:
        raise CheckpointError(
            f"download of {entry.name} from the Hugging Face Hub ({hub.repo_id}, {hub.filename} at revision "
            f"{hub.revision}) failed: {type(e).__name__}: {e}"
        ) from None
    return Path(got)


@contextlib.contextmanager
def _quiet_hub_log() -> Iterator[None]:
    """huggingface_hub's retry warnings off for the block: the outcome is reported once, by us."""
    hub_log = logging.getLogger("huggingface_hub")
    before = hub_log.level
    hub_log.setLevel(max(before, logging.ERROR))
    try:
        yield
    finally:
        hub_log.setLevel(before)


@contextlib.contextmanager
def _hub_progress(enabled: bool) -> Iterator[None]:
    """huggingface_hub's progress bars off for the block when not ``enabled`` (they are process-wide)."""
    from huggingface_hub.utils import are_progress_bars_disabled, disable_progress_bars, enable_progress_bars

    switch = not enabled and not are_progress_bars_disabled()
    if switch:
        disable_progress_bars()
    try:
        yield
    finally:
        if switch:
            enable_progress_bars()


def _from_url(entry: Entry, dest: Path, progress: bool, timeout: float) -> Path:
    """Download ``entry.url`` into ``dest``'s ``.part`` file, resuming what an earlier try left; returns it.

    An interrupted transfer keeps what arrived and says so; a server that ignores the Range request sends the
    whole file, which replaces the partial one.
    """
    from vpengine._version import __version__

    part = dest.with_name(dest.name + ".part")
    offset = part.stat().st_size if part.is_file() else 0
    if entry.size is not None and offset > entry.size:
        offset = 0  # not a prefix of this file: start again
    headers = {"User-Agent": f"vpengine/{__version__} (checkpoint download)"}
    if offset:
        headers["Range"] = f"bytes={offset}-"
    try:
        with _said_if_slow(entry.name, entry.url, timeout):
            resp = urllib.request.urlopen(urllib.request.Request(entry.url, headers=headers), timeout=timeout)
    except urllib.error.HTTPError as e:
        e.close()  # it holds the response's socket
        if e.code == 416 and offset:  # nothing left to send: the partial file is checked as it is
            return part
        raise CheckpointError(
            f"download of {entry.name} from {catalog.shown_url(entry.url)} failed: HTTP {e.code} {e.reason}"
        ) from None
    except (urllib.error.URLError, OSError) as e:  # DNS, refused, TLS, timeout: the server was not reached
        raise Unreachable(catalog.url_host(entry.url), getattr(e, "reason", e)) from None
    with resp:
        if offset and resp.status != 206:
            log.warning("%s: the server does not resume downloads; starting again", entry.name)
            offset = 0
        length = resp.headers.get("Content-Length")
        sent = offset + int(length) if length and length.isdigit() else None
        total = entry.size or sent
        written, error = offset, None
        bar = byte_progress(total, offset, entry.name, progress)
        with part.open("ab" if offset else "wb") as out, bar:
            try:
                while chunk := resp.read(_CHUNK):
                    out.write(chunk)
                    written += len(chunk)
                    bar.update(len(chunk))
            # connection reset, socket timeout, truncated chunked body, disk full
            except (OSError, ValueError, http.client.HTTPException) as e:
                error = e
            out.flush()
            os.fsync(out.fileno())
    # read(n) returns b"" when the server closes early, so a short body shows only in its length.
    if error is not None or written < (sent or total or 0):
        why = f" ({type(error).__name__}: {error})" if error is not None else ""
        raise CheckpointError(
            f"download of {entry.name} from {catalog.shown_url(entry.url)} was interrupted after {human_size(written)} of "
            f"{human_size(total)}{why}; the partial file {part} is kept: fetch again to resume"
        )
    return part


def _remove_quietly(path: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        path.unlink()


@contextlib.contextmanager
def _cache_lock(cache: str | Path, what: str) -> Iterator[None]:
    """Exclusive lock on the cache's weights directory while a file is being written into it.

    Why: two fetches of the same file (two `vpengine weights fetch`, or prefetch in two programs) must not write it
    at once. The lock is an ``flock`` on the directory itself, so no lock file is left behind; it is released if the
    holder dies.
    """
    root = catalog.weights_root(cache)
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


# ------------------------------------------------------------------------------------------ the cache's state
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
    eff = catalog.effective(entry, cache)
    path = entry.path(cache)
    state = cache_status(entry, cache)
    if state != "cached":
        return VerifyResult(entry, path, state.upper(), eff.sha256)
    digest = sha256_file(path, progress, f"verifying {entry.name}")
    if eff.sha256 is None:
        return VerifyResult(entry, path, "UNVERIFIABLE", None, digest)
    if digest != eff.sha256:
        _remove_quietly(stamp_path(path))
        return VerifyResult(entry, path, "MISMATCH", eff.sha256, digest)
    write_stamp(path, digest)
    return VerifyResult(entry, path, "OK", eff.sha256, digest)


# ------------------------------------------------------------------------------------------ a config's files
def checkpoints(cfg: Any) -> list[tuple[str, Entry]]:
    """The catalog checkpoint each model of an engine config loads, as (model name, entry).

    Models with an existing file as checkpoint, random weights or no catalog checkpoint are left out; an unknown
    name fails when the model is built, with the full message.
    """
    if cfg.weights.random_weights:
        return []
    cache = catalog.cache_dir()
    found = []
    for name, mcfg in [("foundation", cfg.foundation_model), *((h.name, h) for h in cfg.heads)]:
        if mcfg.checkpoint and Path(mcfg.checkpoint).expanduser().is_file():
            continue
        entry = catalog.find(mcfg.checkpoint, cache) if mcfg.checkpoint else catalog.default_for(mcfg.model)
        if entry is not None:
            found.append((name, entry))
    return found


def prefetch(cfg: Any, progress: bool = True) -> list[Path]:
    """Fetch (unless offline) and verify every catalog checkpoint of an engine config; returns their paths.

    The explicit way to get a config's files from Python before ``Engine(cfg)`` starts, which never downloads.
    Offline (``weights.offline``, $VPENGINE_OFFLINE) a missing file raises the error that names where to put it.
    """
    cache = catalog.cache_dir()
    paths = []
    for name, entry in checkpoints(cfg):
        if offline(cfg.weights.offline) and not entry.path(cache).is_file():
            raise missing_error(entry, cache, name, offline=True)
        try:  # a file already there is verified (or, without a digest, pinned) without any request
            res = fetch(entry, cache, progress=progress)
        except CheckpointError as e:
            raise CheckpointError(f"{name}: {e}") from None
        if res.pinned == "trust-on-first-use":
            log.warning("%s", trust_notice(res, cache))
        paths.append(res.path)
    return paths
