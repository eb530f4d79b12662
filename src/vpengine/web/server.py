"""The live view's HTTP server: one page, a JSON API, Prometheus metrics, beside a running engine.

::

    GET  /                       the page (no build step, nothing from the internet)
    GET  /api/stats              Engine.stats() as JSON (NaN as null)
    PUT  /api/rate/<model>       {"hz": 5} | {"hz": null} (unlimited) | {"hz": 0} (pause); 400 with the reason
    PUT  /api/priority/<key>     {"priority": 10} (an integer, checks.MIN_PRIORITY..MAX_PRIORITY, higher more
                                 important); key: a head, head@camera (that lane only) or @camera (the camera's
                                 own); 400 with the reason, 404 for an unknown head
    POST /api/heads              a head's config as under ``heads:`` (JSON or YAML): Engine.add_head, 201 once it
                                 is ready; 400 naming the bad field, 409 with no seat free, 422 if it fails to build
    DELETE /api/heads/<head>     Engine.remove_head; 404 for an unknown head, 400 for the last one
    GET  /api/latest/<head>.jpg  the head's newest result as a picture (?width=N, default 640; ?camera=NAME, default
                                 the first camera the head serves; 400 naming the cameras for an unknown one); 204
                                 before its first
    GET  /metrics                Prometheus text format (``vpengine_*``)

The stack is the standard library's threading HTTP server: eight routes and a thread per connection need no
framework, and the engine's process gains no event loop. ``prometheus-client`` (the ``web`` extra) formats the
metrics. Requests do nothing to the engine beyond reading its control block, borrowing one result per picture,
``set_rate``, ``set_priority``, ``add_head`` and ``remove_head``; pictures are bounded (Note [Pictures and frames] in ``pictures.py``).

Note [Who may talk to the view]
~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~~
Bound to loopback without a token, only this machine reaches the server, and a request must also *name* a
loopback host (``Host:`` header): a web page elsewhere that makes the browser resolve its own domain to 127.0.0.1
(DNS rebinding) gets 403, and a cross-site page cannot send ``PUT`` at all (it needs a CORS pre-flight this server
never grants). Bound to any other address, a token is required at start, and every request but the page itself
(which holds no data, and says what is missing) must carry it: ``Authorization: Bearer <token>``, or
``?token=<token>`` in the URL (the page passes it on to its own requests). The token is compared in constant time.
"""

from __future__ import annotations

import hmac
import importlib.util
import ipaddress
import json
import logging
import math
import socket
import threading
import time
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qs, unquote, urlsplit

from vpengine import checks
from vpengine.web.pictures import DEFAULT_WIDTH, FrameLookup, Pictures

if TYPE_CHECKING:
    from vpengine.engine import Engine
    from vpengine.web.pictures import EngineRef

log = logging.getLogger("vpengine.web")

#: How often the page refreshes the stats and each head's picture (the overhead benchmark asks the same).
STATS_PERIOD_S = 0.5
PICTURE_PERIOD_S = 0.25
_MAX_BODY = 4096
_LOOPBACK_NAMES = {"localhost", "localhost.localdomain", "ip6-localhost"}


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or an address) is this machine only."""
    host = host.strip("[]")
    if host.lower() in _LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _json_safe(v: Any) -> Any:
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {str(k): _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if v is None or isinstance(v, (bool, int, str)):
        return v
    return str(v)


def _json(value: Any) -> str:
    """``value`` as JSON writes it (``null``, ``true``, ``"5"``): how a message about a body names what it held."""
    try:
        return json.dumps(value)
    except (TypeError, ValueError):  # pragma: no cover - a parsed body holds JSON values only
        return repr(value)


def _field(body: bytes, key: str, want: str) -> Any:
    """``key`` of a JSON object body; ValueError saying what is accepted (``want``)."""
    if not body.strip():
        raise ValueError(f"expected {want}; the body is empty")
    try:
        doc = json.loads(body)
    except (ValueError, UnicodeDecodeError):
        raise ValueError(f"expected {want}; the body is not JSON") from None
    if not isinstance(doc, dict) or key not in doc:
        raise ValueError(f"expected {want}; got {_json(doc)}"[:300])
    other = sorted(k for k in doc if k != key)
    if other:  # a typo beside the key (or a field meant for another call) is not dropped silently
        raise ValueError(f"{_json(other[0])} is no field of this body; expected {want}; got {_json(doc)}"[:300])
    return doc[key]


def parse_rate(body: bytes, model: str) -> float | None:
    """The ``hz`` of a ``PUT /api/rate/<model>`` body; ValueError saying what is accepted."""
    want = f'a JSON object {{"hz": RATE}} with RATE a number from 0 to {checks.MAX_RATE_HZ:g} (0 pauses) or null (no limit)'
    return checks.rate(model, _field(body, "hz", want), spell=_json)


def parse_priority(body: bytes) -> int:
    """The ``priority`` of a ``PUT /api/priority/<key>`` body; ValueError saying what is accepted."""
    lo, hi = checks.MIN_PRIORITY, checks.MAX_PRIORITY
    want = f'a JSON object {{"priority": P}} with P an integer from {lo} to {hi} (higher: more important)'
    return checks.priority(_field(body, "priority", want), spell=_json)


class WebServer:
    """The live view of an engine, served from a background thread until :meth:`stop` (or the with-block ends).

    ``engine`` is an Engine, or a callable returning the Engine or None (an engine that starts later, as the ROS 2
    core's may: requests get 503 until then). ``frames`` looks up input frames by frame id for overlays and boxes
    (Note [Pictures and frames]); ``frame_color`` is their channel order. ``port`` 0 picks a free one (see
    :attr:`url`). Bound beyond loopback, ``token`` is required (Note [Who may talk to the view]). ``heads_elsewhere``:
    head commands are refused (409) with this reason, because another door owns them.
    """

    def __init__(
        self,
        engine: EngineRef,
        host: str = "127.0.0.1",
        port: int = 0,
        token: str | None = None,
        frames: FrameLookup | None = None,
        frame_color: str = "bgr",
        heads_elsewhere: str | None = None,
    ) -> None:
        if not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"port must be an integer in 0..65535, got {port!r}")
        if importlib.util.find_spec("prometheus_client") is None:
            raise ImportError("the live view needs prometheus-client: pip install 'vpengine[web]'")
        token = token or None
        if not is_loopback(host) and token is None:
            raise ValueError(f"serving on {host!r} reaches beyond this machine: give a token, or bind to 127.0.0.1")
        self._get_engine: Callable[[], Engine | None] = engine if callable(engine) else (lambda: engine)
        self.token = token
        #: why heads are not added or removed here (another door owns them, e.g. the ROS 2 interface, whose topics
        #: must follow); None: they are
        self.heads_elsewhere = heads_elsewhere
        self.pictures = Pictures(frames, frame_color)
        self._page: bytes | None = None
        self._metrics: Any = None
        self._closed = False
        self._conns: set[Any] = set()  # open connections, shut at stop so no handler thread outlives it
        self._conns_lock = threading.Lock()
        handler = type("Handler", (_Handler,), {"view": self})
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        server = type("Server", (ThreadingHTTPServer,), {"address_family": family, "daemon_threads": True})
        self.httpd = server((host.strip("[]"), port), handler)
        self.host, self.port = host, self.httpd.server_address[1]
        # stop() waits for the loop's next look at its shutdown flag: at most this long (a Ctrl-C's last wait)
        self._thread = threading.Thread(
            target=self.httpd.serve_forever, kwargs={"poll_interval": 0.1}, name="vpengine-web", daemon=True
        )
        self._thread.start()
        log.info("live view at %s", self.url)

    @property
    def url(self) -> str:
        """The page's address (``0.0.0.0`` / ``::`` binds answer on every address; this names loopback)."""
        host = {"0.0.0.0": "127.0.0.1", "::": "::1", "[::]": "::1"}.get(self.host, self.host).strip("[]")
        return f"http://{f'[{host}]' if ':' in host else host}:{self.port}/"

    @property
    def engine(self) -> Engine | None:
        return self._get_engine()

    def page(self) -> bytes:
        if self._page is None:
            text = resources.files("vpengine.web").joinpath("page.html").read_text("utf-8")
            text = text.replace("__STATS_MS__", str(round(STATS_PERIOD_S * 1e3)))
            text = text.replace("__PICTURE_MS__", str(round(PICTURE_PERIOD_S * 1e3)))
            self._page = text.encode()
        return self._page

    def metrics(self) -> tuple[bytes, str]:
        from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

        from vpengine.web.metrics import registry

        if self._metrics is None:
            self._metrics = registry(self._running_engine)
        return generate_latest(self._metrics), CONTENT_TYPE_LATEST

    def _running_engine(self) -> Engine | None:
        eng = self._get_engine()
        return eng if eng is not None and eng.running else None

    def stop(self) -> None:
        """Stop serving and close the socket; returns once the server thread has ended. Safe to call twice."""
        if self._closed:
            return
        self._closed = True
        self.httpd.shutdown()
        self.httpd.server_close()
        self._thread.join(timeout=5)
        with self._conns_lock:
            conns = list(self._conns)
        for conn in conns:  # idle keep-alive connections: their threads wake and end
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def __enter__(self) -> WebServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def serve(
    engine: EngineRef,
    port: int = 8080,
    host: str = "127.0.0.1",
    token: str | None = None,
    frames: FrameLookup | None = None,
    frame_color: str = "bgr",
) -> WebServer:
    """Serve the live view of ``engine`` (see :class:`WebServer`); use it as a context manager or call ``stop()``."""
    return WebServer(engine, host, port, token, frames, frame_color)


#: What a 404 lists (docs/web.md says what each does)
_PAGES = (
    "GET / (the live view), /api/stats, /api/latest/<head>.jpg, /metrics; PUT /api/rate/<model>, "
    "/api/priority/<key>; POST /api/heads; DELETE /api/heads/<head>"
)


class _HttpError(Exception):
    def __init__(self, status: HTTPStatus, message: str) -> None:
        super().__init__(message)
        self.status = status


class _Handler(BaseHTTPRequestHandler):
    view: WebServer  # set on the subclass each server makes
    server_version = "vpengine"
    protocol_version = "HTTP/1.1"  # keep-alive: the page's polling reuses its connections
    timeout = 30  # an idle or stalled connection's thread ends after this many seconds

    def setup(self) -> None:
        super().setup()
        with self.view._conns_lock:
            self.view._conns.add(self.connection)

    def finish(self) -> None:
        with self.view._conns_lock:
            self.view._conns.discard(self.connection)
        super().finish()

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("%s %s", self.address_string(), format % args)

    # ---------------------------------------------------------------------------------------- dispatch
    def do_GET(self) -> None:
        self._dispatch("GET")

    def do_PUT(self) -> None:
        self._dispatch("PUT")

    def do_POST(self) -> None:
        self._dispatch("POST")

    def do_DELETE(self) -> None:
        self._dispatch("DELETE")

    def _dispatch(self, method: str) -> None:
        url = urlsplit(self.path)
        query = parse_qs(url.query)
        try:
            body = self._body()
            path = url.path
            self._check_access(query, page=path in ("/", "/index.html"))
            if path == "/" or path == "/index.html":
                self._only(method, "GET")
                self._send(HTTPStatus.OK, self.view.page(), "text/html; charset=utf-8")
            elif path == "/api/stats":
                self._only(method, "GET")
                stats = self._engine().stats()
                self._send_json(HTTPStatus.OK, stats)
            elif path.startswith("/api/rate/"):
                self._only(method, "PUT")
                self._put_rate(unquote(path[len("/api/rate/") :]), body)
            elif path.startswith("/api/priority/"):
                self._only(method, "PUT")
                self._put_priority(unquote(path[len("/api/priority/") :]), body)
            elif path == "/api/heads":
                self._only(method, "POST")
                self._heads_here()
                self._add_head(body)
            elif path.startswith("/api/heads/"):
                self._only(method, "DELETE")
                self._heads_here()
                self._remove_head(unquote(path[len("/api/heads/") :]))
            elif path.startswith("/api/latest/") and path.endswith(".jpg"):
                self._only(method, "GET")
                self._picture(unquote(path[len("/api/latest/") : -len(".jpg")]), query)
            elif path == "/metrics":
                self._only(method, "GET")
                body, ctype = self.view.metrics()
                self._send(HTTPStatus.OK, body, ctype)
            else:
                raise _HttpError(HTTPStatus.NOT_FOUND, f"no such page: {path}; the pages: {_PAGES}")
        except _HttpError as e:
            self._send_json(e.status, {"error": str(e)}, e.status == HTTPStatus.UNAUTHORIZED)
        except (BrokenPipeError, ConnectionResetError):
            pass
        except Exception as e:  # the engine stopped under us, or a bug: a 500 that says what, not a dead thread
            from vpengine.engine import EngineDeadError

            status = (
                HTTPStatus.SERVICE_UNAVAILABLE if isinstance(e, EngineDeadError) else HTTPStatus.INTERNAL_SERVER_ERROR
            )
            if status == HTTPStatus.INTERNAL_SERVER_ERROR:
                log.exception("live view: %s %s failed", method, self.path)
            try:
                self._send_json(status, {"error": f"{type(e).__name__}: {e}"})
            except OSError:
                pass

    def _only(self, method: str, allowed: str) -> None:
        if method != allowed:
            raise _HttpError(HTTPStatus.METHOD_NOT_ALLOWED, f"{method} is not allowed here; use {allowed}")

    def _check_access(self, query: dict[str, list[str]], page: bool) -> None:
        """Note [Who may talk to the view]."""
        view = self.view
        if view.token is None:
            host = self.headers.get("Host", "")
            name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
            if host and not is_loopback(name):
                raise _HttpError(HTTPStatus.FORBIDDEN, f"this view answers to loopback names only, not {host!r}")
            return
        if page:
            return  # the page holds no data; what it asks for needs the token
        given = ""
        auth = self.headers.get("Authorization", "")
        if auth.lower().startswith("bearer "):
            given = auth[7:].strip()
        elif query.get("token"):
            given = query["token"][0]
        if not hmac.compare_digest(given.encode(), view.token.encode()):
            raise _HttpError(
                HTTPStatus.UNAUTHORIZED,
                "a token is required: Authorization: Bearer <token>, or ?token=<token> in the address",
            )

    def _engine(self) -> Engine:
        eng = self.view.engine
        if eng is None or not eng.running:
            state = "not started yet" if eng is None else "not running"
            raise _HttpError(HTTPStatus.SERVICE_UNAVAILABLE, f"the engine is {state}")
        return eng

    # ------------------------------------------------------------------------------------------ routes
    def _body(self) -> bytes:
        """The request's body, read whole before anything can fail, so a kept-alive connection stays in step."""
        if self.headers.get("Transfer-Encoding"):
            self.close_connection = True
            raise _HttpError(HTTPStatus.LENGTH_REQUIRED, "send the body with a Content-Length")
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            length = -1
        if not 0 <= length <= _MAX_BODY:
            self.close_connection = True
            raise _HttpError(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"the body must be 0..{_MAX_BODY} bytes")
        return self.rfile.read(length) if length else b""

    def _put_rate(self, model: str, body: bytes) -> None:
        eng = self._engine()
        try:
            hz = parse_rate(body, model)
            eng.set_rate(model, hz)
        except (ValueError, KeyError) as e:
            raise _HttpError(HTTPStatus.BAD_REQUEST, str(e.args[0]) if e.args else str(e)) from None
        log.info("live view: %s rate set to %s", model, "unlimited" if hz is None else f"{hz:g} Hz")
        self._send_json(HTTPStatus.OK, {"model": model, "hz": eng.rate(model)})

    def _put_priority(self, key: str, body: bytes) -> None:
        eng = self._engine()
        try:
            head, camera = checks.priority_target(key)
        except ValueError as e:  # an empty key
            raise _HttpError(HTTPStatus.BAD_REQUEST, str(e)) from None
        try:
            priority = parse_priority(body)
            eng.set_priority(head, priority, camera=camera)
        except KeyError as e:  # an unknown head
            raise _HttpError(HTTPStatus.NOT_FOUND, str(e.args[0]) if e.args else str(e)) from None
        except ValueError as e:
            raise _HttpError(HTTPStatus.BAD_REQUEST, str(e)) from None
        log.info("live view: priority of %s set to %d", key, priority)
        self._send_json(HTTPStatus.OK, {"head": head, "camera": camera, "priority": priority})

    def _heads_here(self) -> None:
        if self.view.heads_elsewhere is not None:
            raise _HttpError(HTTPStatus.CONFLICT, self.view.heads_elsewhere)

    def _add_head(self, body: bytes) -> None:
        from vpengine.engine import EngineDeadError, EngineStartError

        eng = self._engine()
        try:
            name = eng.add_head(body.decode("utf-8", "replace"))  # JSON is YAML: one parser takes both
        except EngineStartError as e:
            raise _HttpError(HTTPStatus.UNPROCESSABLE_ENTITY, str(e)) from None
        except EngineDeadError:
            raise
        except RuntimeError as e:  # no seat free
            raise _HttpError(HTTPStatus.CONFLICT, str(e)) from None
        except ValueError as e:  # ConfigError too
            raise _HttpError(HTTPStatus.BAD_REQUEST, str(e)) from None
        log.info("live view: head %s added", name)
        self._send_json(HTTPStatus.CREATED, {"head": name})

    def _remove_head(self, name: str) -> None:
        eng = self._engine()
        try:
            eng.remove_head(name)
        except KeyError as e:
            raise _HttpError(HTTPStatus.NOT_FOUND, str(e.args[0]) if e.args else str(e)) from None
        except ValueError as e:
            raise _HttpError(HTTPStatus.BAD_REQUEST, str(e)) from None
        log.info("live view: head %s removed", name)
        self._send_json(HTTPStatus.OK, {"removed": name})

    def _picture(self, head: str, query: dict[str, list[str]]) -> None:
        eng = self._engine()
        width = DEFAULT_WIDTH
        if "width" in query:
            try:
                width = int(query["width"][0])
            except ValueError:
                width = 0
            if not 16 <= width <= 8192:
                raise _HttpError(
                    HTTPStatus.BAD_REQUEST, f"width must be an integer in 16..8192, got {query['width'][0]!r}"
                )
        try:
            eng.head_info(head)  # KeyError for an unknown head
            served = eng.lanes.served(head)
        except KeyError as e:
            raise _HttpError(HTTPStatus.NOT_FOUND, str(e.args[0])) from None
        # Note [Pictures and frames]: one picture per camera and head, never the newest of any camera's
        camera = query["camera"][0] if "camera" in query else served[0]
        if camera not in eng.cameras:
            raise _HttpError(HTTPStatus.BAD_REQUEST, f"no camera named {camera!r}; cameras: {eng.cameras}")
        if camera not in served:
            raise _HttpError(HTTPStatus.NOT_FOUND, f"{head!r} serves cameras {served}, not {camera!r}")
        pic = self.view.pictures.latest(eng, head, width, camera)
        if pic is None:
            self._send(HTTPStatus.NO_CONTENT, b"", "image/jpeg")
            return
        self._send(
            HTTPStatus.OK,
            pic.jpeg,
            "image/jpeg",
            extra={
                "X-Frame-Id": str(pic.frame_id),
                "X-Camera": camera,
                "X-Capture-Time": f"{pic.capture_time:.6f}",
                "X-Latency-Ms": f"{pic.latency * 1e3:.2f}",
                "X-On-Frame": "1" if pic.on_frame else "0",
                "X-Age-Ms": f"{(time.monotonic() - pic.made_at) * 1e3:.0f}",
            },
        )

    # ------------------------------------------------------------------------------------------ replies
    def _send_json(self, status: HTTPStatus, doc: Any, challenge: bool = False) -> None:
        body = json.dumps(_json_safe(doc), allow_nan=False).encode()
        extra = {"WWW-Authenticate": "Bearer"} if challenge else {}
        self._send(status, body, "application/json", extra)

    def _send(self, status: HTTPStatus, body: bytes, ctype: str, extra: dict[str, str] | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if body and self.command != "HEAD":
            self.wfile.write(body)
