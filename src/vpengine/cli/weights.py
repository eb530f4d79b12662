"""``vpengine weights``: the checkpoint catalog and the local cache.

* ``list``: every catalog entry with its size, licence and whether it is cached;
* ``fetch NAME [NAME...]`` or ``fetch --config FILE``: download, verify (sha256) and cache the named files, or
  every catalog file a config loads (the engine itself never downloads);
* ``verify [NAME...]``: re-hash cached files, report OK / MISMATCH / MISSING, exit 1 on any problem;
* ``path NAME``: where the file of NAME lives (exit 1 if it is not there yet).

An entry of the shipped catalog without a published sha256, fetched over HTTPS, is trusted on first use: the digest
of what is fetched is recorded in the cache, said in one line, and checked on every later use. Any other entry
without one (a custom ``--url``, a $VPENGINE_CATALOG entry, a plain-HTTP source) needs ``--sha256 HEX`` or
``--trust-on-first-use``. Offline or with the server unreachable, each file gets one line: why, the path to place it
at and the URL to get it from.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any


def add_arguments(p: argparse.ArgumentParser) -> None:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--cache",
        metavar="DIR",
        help="checkpoint cache: sets $VPENGINE_CACHE for this command (default: $VPENGINE_CACHE, else "
        "$XDG_CACHE_HOME/vpengine)",
    )
    common.add_argument("--no-progress", action="store_true", help="no progress bars")
    sub = p.add_subparsers(dest="weights_command", metavar="ACTION")

    ls = sub.add_parser("list", parents=[common], help="catalog entries: size, licence, cached or not")
    ls.add_argument("--json", action="store_true", help="print JSON instead of a table")

    f = sub.add_parser(
        "fetch", parents=[common], help="download, verify and cache checkpoints (resumes partial downloads)"
    )
    f.add_argument("names", nargs="*", metavar="NAME", help="catalog names (`vpengine weights list`)")
    f.add_argument(
        "--config",
        "-c",
        metavar="FILE",
        help="also every catalog checkpoint this engine config loads (its weights.offline applies)",
    )
    f.add_argument(
        "--sha256",
        metavar="HEX",
        help="expected sha256 for an entry the catalog has none for (or a custom --url entry); recorded in the cache",
    )
    f.add_argument(
        "--trust-on-first-use",
        action="store_true",
        help="for an entry without a published sha256: accept the digest of what is there now, even over an "
        "earlier pin (shipped catalog entries fetched over HTTPS are trusted on first use without it)",
    )
    f.add_argument("--url", help="download a custom entry NAME from this URL (needs --sha256 or --trust-on-first-use)")
    f.add_argument("--file", help="file name of a custom --url entry (default: the URL's last path part)")
    f.add_argument("--force", action="store_true", help="download again even if a verified copy is cached")
    f.add_argument(
        "--offline",
        action="store_true",
        help="never download (also $VPENGINE_OFFLINE=1 or $HF_HUB_OFFLINE=1)",
    )
    f.add_argument("--timeout", type=float, default=60.0, help="network timeout in seconds (default 60)")

    v = sub.add_parser("verify", parents=[common], help="re-hash cached checkpoints; exit 1 on any problem")
    v.add_argument("names", nargs="*", metavar="NAME", help="entries to check (default: every cached or partial one)")

    pa = sub.add_parser("path", parents=[common], help="the cache path of a checkpoint (exit 1 if not there)")
    pa.add_argument("name", metavar="NAME")
    p.set_defaults(weights_help=p.format_help)


def _cache() -> Path:
    from vpengine.models.catalog import cache_dir

    return cache_dir()


def _entries(cache: Path) -> list[Any]:
    """The active catalog followed by the custom entries recorded in this cache."""
    from vpengine.models import catalog

    cat = catalog.active()
    return [*cat, *(e for e in catalog.local_catalog(cache) if e.name not in cat)]


def _lookup(name: str, cache: Path) -> Any:
    from vpengine.models import catalog
    from vpengine.models.weights import CheckpointError

    entry = catalog.find(name, cache)
    if entry is None:
        known = ", ".join(e.name for e in _entries(cache))
        raise CheckpointError(f"{name!r} is not a catalog name; known: {known}")
    return entry


def _size(n: int | None) -> str:
    from vpengine.models.catalog import human_size

    return "?" if n is None else human_size(n)


def _cached_text(entry: Any, cache: Path) -> str:
    from vpengine.models import catalog
    from vpengine.models.download import cache_status

    state = cache_status(entry, cache)
    if state == "partial":
        part = entry.path(cache).with_name(entry.file + ".part").stat().st_size
        size = catalog.effective(entry, cache).size
        return f"partial {100 * part // size}%" if size else f"partial {_size(part)}"
    return {"cached": "yes", "missing": "no"}[state]


def _digest_kind(entry: Any, cache: Path, listed: Any) -> str:
    """How ``entry``'s digest is known; ``listed``: the active catalog (read once: $VPENGINE_CATALOG is files)."""
    from vpengine.models import catalog

    if entry.sha256 is not None and entry.name in listed:
        return "catalog"
    return "pinned" if catalog.effective(entry, cache).sha256 else "none"  # a custom entry's is the user's word


def cmd_list(args: argparse.Namespace) -> int:
    from vpengine.models import catalog
    from vpengine.models.catalog import shown_url

    cache = _cache()
    rows = []
    listed = catalog.active()
    for e in _entries(cache):
        eff = catalog.effective(e, cache)
        rows.append(
            {
                "name": e.name,
                "size": eff.size,
                "licence": e.licence,
                "cached": _cached_text(e, cache),
                "sha256": eff.sha256,
                "digest": _digest_kind(e, cache, listed),
                "recipes": list(e.recipes),
                "url": shown_url(e.url),
                "path": str(e.path(cache)),
            }
        )
    if args.json:
        print(json.dumps({"cache": str(cache), "entries": rows}, indent=2))
        return 0
    w = max(len(r["name"]) for r in rows) if rows else 4
    print(f"cache: {cache}")
    print(f"{'name':{w}s}  {'size':>10s}  {'licence':12s}  {'cached':11s}  {'sha256':7s}  recipes")
    for r in rows:
        print(
            f"{r['name']:{w}s}  {_size(r['size']):>10s}  {r['licence']:12s}  {r['cached']:11s}  "
            f"{r['digest']:7s}  {', '.join(r['recipes']) or '-'}"
        )
    print(
        "(sha256: catalog = published digest (or $VPENGINE_CATALOG's); pinned = recorded by you (--sha256, or "
        "trusted on first use); none = not known yet: a shipped HTTPS entry is trusted on first use, any other needs "
        "--sha256 or --trust-on-first-use. cached: the file is there; `vpengine weights verify` checks it)"
    )
    return 0


def cmd_fetch(args: argparse.Namespace) -> int:
    from vpengine.models import download
    from vpengine.models.catalog import CatalogError, custom_entry, shown_url
    from vpengine.models.weights import CheckpointError, place_hint

    def usage(msg: str) -> int:
        print(f"vpengine weights fetch: {msg}", file=sys.stderr)
        return 2

    if not args.names and not args.config:
        return usage("name the checkpoints to fetch (NAME...) or give --config FILE")
    if (args.sha256 or args.url or args.file) and (len(args.names) != 1 or args.config):
        return usage("--sha256, --url and --file apply to one NAME at a time, without --config")
    if args.file and not args.url:
        return usage("--file only applies to a custom --url entry")
    is_offline = download.offline(args.offline)
    cache = _cache()
    wanted: list[tuple[str, Any]] = [(name, None) for name in args.names]
    if args.config:
        from vpengine.config import load_config

        cfg = load_config(args.config)
        is_offline = is_offline or cfg.weights.offline
        names = set(args.names)
        for _model, entry in download.checkpoints(cfg):
            if entry.name not in names:
                names.add(entry.name)
                wanted.append((entry.name, entry))
        # a checkpoint that is neither a file nor a catalog name: nothing fetches it, and the engine will not start
        # without it. Said, not failed: the config's own order may make it later (the shipped config's detector is
        # trained after its other files are fetched)
        try:
            missing = unresolvable(cfg)
            planned = True
        except Exception as e:  # the engine's start would stop here too: the config is wrong, whatever is fetched
            print(f"vpengine weights fetch: {args.config}: the engine would not start: {e}", file=sys.stderr)
            missing, planned = [], False
        for line in missing:
            print(f"vpengine weights fetch: WARNING: not fetched, {line}", file=sys.stderr)
        if len(wanted) == len(args.names) and not missing and planned:
            print(f"{args.config} loads no catalog checkpoint (files, random weights or none)")
    else:
        planned = True
    failed = 0 if planned else 1
    unreachable: dict[str, download.Unreachable] = {}  # host -> how it failed: one wait per host, not per file
    for name, entry in wanted:
        try:
            if args.url:
                if is_offline:
                    raise CheckpointError(f"offline mode: not downloading {name} from {shown_url(args.url)}")
                entry = custom_entry(name, args.url, file=args.file)
            elif entry is None:
                entry = _lookup(name, cache)
            if is_offline and (args.force or not entry.path(cache).is_file()):
                raise CheckpointError(f"offline mode, not downloaded: {place_hint(entry, cache)}")
            host = download.source_host(entry)
            if host in unreachable and (args.force or not entry.path(cache).is_file()):
                raise download.Unreachable(host, unreachable[host].why, place_hint(entry, cache))
            res = download.fetch(
                entry,
                cache,
                sha256=args.sha256,
                trust_on_first_use=args.trust_on_first_use,
                force=args.force,
                progress=not args.no_progress,
                timeout=args.timeout,
            )
        except (CheckpointError, CatalogError) as e:
            if isinstance(e, download.Unreachable):
                unreachable[e.host] = e
            print(f"vpengine weights fetch: {name}: {e}", file=sys.stderr)
            failed += 1
            continue
        how = "downloaded" if res.downloaded else "already cached"
        if res.pinned == "trust-on-first-use":
            print(f"{entry.name}: {how}: {res.path}")
            print(f"vpengine weights fetch: WARNING: {download.trust_notice(res, cache)}", file=sys.stderr)
        else:
            print(f"{entry.name}: {how}, sha256 {res.sha256} verified: {res.path}")
        if res.pinned == "--sha256":
            print(f"{entry.name}: sha256 from --sha256 recorded in {cache}")
        if entry.licence not in ("Apache-2.0", "MIT", "BSD-3-Clause") and res.downloaded:
            print(f"{entry.name}: licence {entry.licence}: check that your use is allowed")
    return 1 if failed else 0


def cmd_verify(args: argparse.Namespace) -> int:
    from vpengine.models.download import cache_status, verify
    from vpengine.models.weights import CheckpointError

    cache = _cache()
    named = bool(args.names)
    problems = 0
    if named:
        entries = []
        for name in args.names:
            try:
                entries.append(_lookup(name, cache))
            except CheckpointError as err:
                print(f"UNKNOWN      {name}: {err}")
                problems += 1
    else:
        entries = [e for e in _entries(cache) if cache_status(e, cache) != "missing"]
        if not entries:
            print(f"no checkpoint is cached in {cache}")
            return 0
    for e in entries:
        r = verify(e, cache, progress=not args.no_progress)
        if r.status == "OK":
            line = f"{r.path}"
        elif r.status == "MISMATCH":
            line = (
                f"expected sha256 {r.expected}, got {r.actual} ({r.path}); "
                f"`vpengine weights fetch {e.name} --force` replaces it"
            )
        elif r.status == "MISSING":
            line = f"not in the cache ({r.path}); `vpengine weights fetch {e.name}` gets it"
        elif r.status == "PARTIAL":
            line = f"interrupted download only; `vpengine weights fetch {e.name}` resumes it"
        else:
            line = (
                f"sha256 {r.actual} cannot be checked: no digest is known; pin one with "
                f"`vpengine weights fetch {e.name} --sha256 HEX` or `--trust-on-first-use`"
            )
        print(f"{r.status:12s} {e.name}: {line}")
        if r.problem or (named and r.status == "PARTIAL"):
            problems += 1
    if problems:
        print(f"{problems} problem(s)", file=sys.stderr)
    return 1 if problems else 0


def cmd_path(args: argparse.Namespace) -> int:
    from vpengine.models.catalog import shown_url

    cache = _cache()
    entry = _lookup(args.name, cache)
    path = entry.path(cache)
    print(path)
    if not path.is_file():
        print(
            f"{entry.name} is not cached yet: `vpengine weights fetch {entry.name}`, or place the file at the "
            f"path above (from {shown_url(entry.source_url())})",
            file=sys.stderr,
        )
        return 1
    return 0


def main(args: argparse.Namespace) -> int:
    commands = {"list": cmd_list, "fetch": cmd_fetch, "verify": cmd_verify, "path": cmd_path}
    if not getattr(args, "weights_command", None):
        print(args.weights_help())
        return 2
    if not args.cache:
        return commands[args.weights_command](args)
    before = os.environ.get("VPENGINE_CACHE")
    os.environ["VPENGINE_CACHE"] = args.cache  # the one way to choose the cache, for this command only
    try:
        return commands[args.weights_command](args)
    finally:
        if before is None:
            del os.environ["VPENGINE_CACHE"]
        else:
            os.environ["VPENGINE_CACHE"] = before


def unresolvable(cfg: Any) -> list[str]:
    """A line per model of an engine config whose checkpoint is neither an existing file nor a catalog name: nothing
    fetches it, and the engine will not start until it is there. Asked as the engine asks (each planned model's
    :meth:`Model.needed_checkpoint`; a checkpoint a model declares none for is not needed), and each line is the one
    the engine's start would give, starting with the model's name. A config that does not plan raises the error the
    engine's start would."""
    if cfg.weights.random_weights:
        return []
    from vpengine.models import catalog
    from vpengine.models.weights import CheckpointError, locate_checkpoint
    from vpengine.runtime.plan import make_plan

    plan = make_plan(cfg)
    cache = catalog.cache_dir()
    lines = []
    for name, model in {"foundation": plan.foundation, **plan.heads}.items():
        mcfg = cfg.model(name)
        try:
            needed = model.needed_checkpoint(mcfg)
            if needed is None or Path(needed).expanduser().is_file() or catalog.find(needed, cache) is not None:
                continue
            locate_checkpoint(name, mcfg.model, str(needed))
        except CheckpointError as e:
            lines.append(str(e) if str(e).startswith(f"{name}: ") else f"{name}: {e}")
    return lines
