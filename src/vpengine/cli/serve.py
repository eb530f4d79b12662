"""``--serve [HOST:]PORT``: the live view (:mod:`vpengine.web`) beside any command that runs an engine.

::

    add_serve_arguments(parser)                      # --serve, --serve-token
    ...
    with serving(serve_options(args), engine, frames=lookup):
        ...                                          # the engine runs; the view answers at the printed address
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

TOKEN_ENV = "VPENGINE_SERVE_TOKEN"


@dataclass(frozen=True)
class ServeOptions:
    host: str
    port: int
    token: str | None = None


def parse_address(text: str) -> tuple[str, int]:
    """``PORT``, ``HOST:PORT`` or ``[IPV6]:PORT`` -> (host, port); the host defaults to 127.0.0.1."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host = "127.0.0.1"
    elif host.count(":") and not (host.startswith("[") and host.endswith("]")):
        raise ValueError(f"--serve {text!r}: write an IPv6 address in brackets, e.g. [::1]:8080")
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"--serve {text!r}: expected [HOST:]PORT with PORT 0..65535, e.g. 8080 or 0.0.0.0:8080")
    return host.strip("[]") or "127.0.0.1", int(port)


def add_serve_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--serve",
        metavar="[HOST:]PORT",
        help="serve a live view (per-model rates and latencies, rate controls, each head's newest picture, "
        "/metrics for Prometheus) at http://HOST:PORT/ (HOST defaults to 127.0.0.1; needs vpengine[web])",
    )
    p.add_argument(
        "--serve-token",
        metavar="TOKEN",
        help=f"token every request to the view must carry (default: ${TOKEN_ENV}); required when HOST is "
        "not loopback",
    )


def serve_options(args: argparse.Namespace) -> ServeOptions | None:
    """What ``--serve`` and ``--serve-token`` ask for (None: no view); ValueError for a bad address."""
    if not getattr(args, "serve", None):
        return None
    from vpengine.web.server import is_loopback

    host, port = parse_address(args.serve)
    token = args.serve_token or os.environ.get(TOKEN_ENV) or None
    if token is None and not is_loopback(host):
        raise ValueError(
            f"--serve {args.serve}: {host} reaches beyond this machine, so the view needs a token: give "
            f"--serve-token TOKEN or set ${TOKEN_ENV} (or serve on 127.0.0.1)"
        )
    return ServeOptions(host, port, token)


@contextlib.contextmanager
def serving(
    options: ServeOptions | None,
    engine: Any,
    frames: Callable[[int], np.ndarray | None] | None = None,
    frame_color: str = "bgr",
) -> Iterator[Any]:
    """The live view of ``engine`` (an Engine, or a callable returning it or None) while the block runs; yields
    the :class:`vpengine.web.WebServer`, or None when ``options`` is None. ``frames``: frame id -> the input frame
    (``frame_color`` order), for overlays and boxes (Note [Pictures and frames] in ``vpengine.web.pictures``)."""
    if options is None:
        yield None
        return
    from vpengine.web import WebServer

    try:
        server = WebServer(engine, options.host, options.port, options.token, frames, frame_color)
    except ImportError as e:
        raise RuntimeError(f"--serve: {e}") from None
    except OSError as e:
        raise RuntimeError(f"--serve {options.host}:{options.port}: cannot listen there ({e})") from None
    print(f"vpengine: live view at {server.url}", file=sys.stderr, flush=True)
    try:
        yield server
    finally:
        server.stop()
