"""``--serve [HOST:]PORT`` (and ``--foxglove PORT``): the live view (:mod:`vpengine.web`) beside any command that
runs an engine.

::

    add_serve_arguments(parser)                      # --serve, --serve-token, --foxglove
    ...
    with serving(options := serve_options(args), engine, frames=lookup) as server:
        ...                                          # the engine runs; the view answers at the printed address
        keep_serving(options, server)                # a run that ended: its last state until Ctrl-C (Note [Serving on])
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import os
import signal
import socket
import sys
import threading
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
    address, or a non-loopback one without a token; ModuleNotFoundError (which ``vpengine``'s ``EXTRAS`` turns into
    the extra to install) when the view's dependency is missing."""
    web = parse_address(args.serve) if getattr(args, "serve", None) else None
    fox = parse_address(args.foxglove, "--foxglove") if getattr(args, "foxglove", None) else None
    if web is None and fox is None:
        return None
    if web is not None:
        _require("prometheus_client")  # before the engine starts, not after a wait for it
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
    if web is not None and fox is not None and web == fox and web[1] != 0:
        raise ValueError(f"--serve {args.serve} and --foxglove {args.foxglove}: one port cannot serve both views")
    for flag, text, address in (("--serve", args.serve, web), ("--foxglove", getattr(args, "foxglove", None), fox)):
        if address is not None:
            _check_listen(flag, text, address)
    return ServeOptions(web, token, fox)


def _check_listen(flag: str, text: str, address: tuple[str, int]) -> None:
    """ValueError unless this process can listen at ``address`` (``text`` as given) now: a port in use, or an
    address that is not this machine's, is said before the engine starts (a compiled GPU config takes minutes to),
    not after. Bound as the view's server binds (web/server.py: IPv6 for a host with a colon, else IPv4, address
    reuse on); it binds again when it starts, and what takes the port in between is said then."""
    host, port = address
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            s.bind((host, port))
    except OSError as e:
        raise ValueError(f"{flag} {text}: cannot listen there ({e})") from None


@contextlib.contextmanager
def serving(
    options: ServeOptions | None,
    engine: Any,
    frames: Callable[[int], np.ndarray | None] | None = None,
    frame_color: str = "bgr",
    heads_elsewhere: str | None = None,
) -> Iterator[Any]:
    """The live view of ``engine`` (an Engine, or a callable returning it or None) while the block runs; yields
    the :class:`vpengine.web.WebServer` (None without ``--serve``). ``frames``: frame id -> the input frame
    (``frame_color`` order), for overlays and boxes (Note [Pictures and frames] in ``vpengine.web.pictures``).
    ``heads_elsewhere``: why the view refuses head commands (another door owns them)."""
    with contextlib.ExitStack() as stack:
        server = fox = None
        if options is not None and options.web is not None:
            from vpengine.web import WebServer

            host, port = options.web
            server = _start(
                "--serve", options.web, WebServer, engine, host, port, options.token, frames, frame_color,
                heads_elsewhere,
            )  # fmt: skip
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


def _require(module: str) -> None:
    """ModuleNotFoundError naming ``module`` when it cannot be imported, for ``vpengine``'s table of extras."""
    try:
        found = importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # an import hook that refuses it, a module that failed half-way
        found = False
    if not found:
        raise ModuleNotFoundError(f"No module named {module!r}", name=module)


def _start(flag: str, address: tuple[str, int], make: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    try:
        return make(*args, **kwargs)
    except ModuleNotFoundError:
        raise  # its name finds the extra in vpengine's table (cli/main.py's EXTRAS); its text alone names none
    except ImportError as e:
        raise RuntimeError(f"{flag}: {e}") from None
    except OSError as e:
        raise RuntimeError(f"{flag} {address[0]}:{address[1]}: cannot listen there ({e})") from None


# Note [Serving on]: a run over a file, a folder, a bag or a counted synthetic scene ends in seconds, often before
# anyone could open its live view. So once such a run has ended on its own (not by Ctrl-C), its summary printed and
# its files written, the view stays up on the engine, now idle: the page, /api/stats and /metrics show the run's
# counters and each head's last picture, until Ctrl-C or SIGTERM (either ends the wait; the run's exit status is
# unchanged). The engine is kept rather than a snapshot of it, so every route answers as during the run (the
# achieved rates fall to 0, truthfully: nothing runs; rates can still be set, with nothing left to run).
def keep_serving(options: ServeOptions, server: Any) -> None:
    """After a run that ended on its own: say so, then keep the view (``server``, :func:`serving`'s) up until
    SIGINT or SIGTERM (Note [Serving on]). Returns at once off the main thread, where no signal can end the wait."""
    if threading.current_thread() is not threading.main_thread():
        return
    views = [f"live view stays at {server.url}"] if server is not None else []
    if options.foxglove is not None:
        views.append("Foxglove view stays up")  # its address was printed when it started
    done = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        done.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        print(
            f"vpengine: the run has ended; its {' and its '.join(views)} until Ctrl-C",
            file=sys.stderr,
            flush=True,
        )
        while not done.wait(0.5):  # a timed wait: signal handlers run between waits on every platform
            pass
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
