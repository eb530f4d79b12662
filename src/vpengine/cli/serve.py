"""``--serve [HOST:]PORT`` (and ``--foxglove PORT``): the live view (:mod:`vpengine.web`) beside any command that
runs an engine.

::

    add_serve_arguments(parser)                      # --serve, --serve-token, --foxglove
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
    #: (host, port) of the page, API and metrics; None: not served
    web: tuple[str, int] | None
    token: str | None = None
    #: (host, port) of the Foxglove WebSocket server; None: not served
    foxglove: tuple[str, int] | None = None


def parse_address(text: str, flag: str = "--serve") -> tuple[str, int]:
    """``PORT``, ``HOST:PORT`` or ``[IPV6]:PORT`` -> (host, port); the host defaults to 127.0.0.1."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host = "127.0.0.1"
    elif host.count(":") and not (host.startswith("[") and host.endswith("]")):
        raise ValueError(f"{flag} {text!r}: write an IPv6 address in brackets, e.g. [::1]:8080")
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{flag} {text!r}: expected [HOST:]PORT with PORT 0..65535, e.g. 8080 or 0.0.0.0:8080")
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
        help=f"token every request to the view must carry (default: ${TOKEN_ENV}); required when HOST is not loopback",
    )
    p.add_argument(
        "--foxglove",
        metavar="[127.0.0.1:]PORT",
        help="also send each head's picture (and detections as image annotations) to Foxglove over a WebSocket "
        "server on this loopback port (needs vpengine[foxglove])",
    )


def serve_options(args: argparse.Namespace) -> ServeOptions | None:
    """What ``--serve``, ``--serve-token`` and ``--foxglove`` ask for (None: no view); ValueError for a bad
    address, or a non-loopback one without a token."""
    web = parse_address(args.serve) if getattr(args, "serve", None) else None
    fox = parse_address(args.foxglove, "--foxglove") if getattr(args, "foxglove", None) else None
    if web is None and fox is None:
        return None
    from vpengine.web.server import is_loopback

    token = args.serve_token or os.environ.get(TOKEN_ENV) or None
    if web is not None and token is None and not is_loopback(web[0]):
        raise ValueError(
            f"--serve {args.serve}: {web[0]} reaches beyond this machine, so the view needs a token: give "
            f"--serve-token TOKEN or set ${TOKEN_ENV} (or serve on 127.0.0.1)"
        )
    if fox is not None and not is_loopback(fox[0]):
        raise ValueError(
            f"--foxglove {args.foxglove}: Foxglove's WebSocket protocol has no authentication, so it is served on "
            "loopback only; forward the port to reach it from elsewhere (ssh -L)"
        )
    return ServeOptions(web, token, fox)


@contextlib.contextmanager
def serving(
    options: ServeOptions | None,
    engine: Any,
    frames: Callable[[int], np.ndarray | None] | None = None,
    frame_color: str = "bgr",
) -> Iterator[Any]:
    """The live view of ``engine`` (an Engine, or a callable returning it or None) while the block runs; yields
    the :class:`vpengine.web.WebServer` (None without ``--serve``). ``frames``: frame id -> the input frame
    (``frame_color`` order), for overlays and boxes (Note [Pictures and frames] in ``vpengine.web.pictures``)."""
    with contextlib.ExitStack() as stack:
        server = fox = None
        if options is not None and options.web is not None:
            from vpengine.web import WebServer

            host, port = options.web
            server = _start("--serve", options.web, WebServer, engine, host, port, options.token, frames, frame_color)
            stack.callback(server.stop)
            print(f"vpengine: live view at {server.url}", file=sys.stderr, flush=True)
        if options is not None and options.foxglove is not None:
            from vpengine.web.foxglove import FoxgloveView

            host, port = options.foxglove
            pictures = server.pictures if server is not None else None  # one bound for both
            fox = _start(
                "--foxglove", options.foxglove, FoxgloveView, engine, host, port, frames, frame_color, pictures=pictures
            )
            stack.callback(fox.stop)
            print(f"vpengine: Foxglove view at {fox.url}", file=sys.stderr, flush=True)
        yield server


def _start(flag: str, address: tuple[str, int], make: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    try:
        return make(*args, **kwargs)
    except ImportError as e:
        raise RuntimeError(f"{flag}: {e}") from None
    except OSError as e:
        raise RuntimeError(f"{flag} {address[0]}:{address[1]}: cannot listen there ({e})") from None
