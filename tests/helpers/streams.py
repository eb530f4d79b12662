"""Real streams on 127.0.0.1 for the live sources (vpengine.io.live): a network camera sending MJPEG over HTTP, and a
web server for video files that answers range requests as real ones do (an mp4 is read from both ends)."""

from __future__ import annotations

import http.server
import re
import socket
import threading
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np


class _Server:
    def __init__(self, handler: type[http.server.BaseHTTPRequestHandler]) -> None:
        handler.log_message = lambda *a: None  # type: ignore[method-assign]
        self.http = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.http.daemon_threads = True
        self.port = self.http.server_port
        self._thread = threading.Thread(target=self.http.serve_forever, args=(0.05,), daemon=True)

    def __enter__(self) -> Any:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.http.shutdown()
        self.http.server_close()


class MjpegCamera(_Server):
    """``url`` sends ``width``x``height`` JPEG frames at ``fps`` as multipart/x-mixed-replace (how network cameras
    serve MJPEG); frame i is grey level ``8 * i % 256``. After ``stall_after`` frames it keeps the connection open and
    sends nothing more (a camera that hangs); after ``close_after`` it closes it."""

    def __init__(
        self,
        width: int = 64,
        height: int = 48,
        fps: float = 20.0,
        stall_after: int | None = None,
        close_after: int | None = None,
    ) -> None:
        camera = self
        self.stop = threading.Event()

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                i = 0
                while not camera.stop.is_set() and i != close_after:
                    if i == stall_after:
                        camera.stop.wait()
                        return
                    _, jpg = cv2.imencode(".jpg", np.full((height, width, 3), 8 * i % 256, np.uint8))
                    head = f"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpg)}\r\n\r\n".encode()
                    try:
                        self.wfile.write(head + jpg.tobytes() + b"\r\n")
                        self.wfile.flush()
                    except OSError:  # the reader hung up
                        return
                    i += 1
                    time.sleep(1.0 / fps)

        super().__init__(Handler)
        self.url = f"http://127.0.0.1:{self.port}/cam"

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        super().__exit__(*exc)


class FileServer(_Server):
    """Serves the files of ``folder`` at ``url + NAME``, with range requests unless ``ranges`` is False (then an mp4
    whose index is at its end cannot be read over it)."""

    def __init__(self, folder: Path, ranges: bool = True) -> None:
        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:
                path = folder / self.path.lstrip("/")
                if not path.is_file():
                    self.send_error(404)
                    return
                data = path.read_bytes()
                m = re.match(r"bytes=(\d+)-(\d*)", self.headers.get("Range", "")) if ranges else None
                start, end = (int(m.group(1)), int(m.group(2) or len(data) - 1)) if m else (0, len(data) - 1)
                self.send_response(206 if m else 200)
                self.send_header("Accept-Ranges", "bytes" if ranges else "none")
                self.send_header("Content-Type", "video/mp4")
                self.send_header("Content-Length", str(end - start + 1))
                if m:
                    self.send_header("Content-Range", f"bytes {start}-{end}/{len(data)}")
                self.end_headers()
                try:
                    self.wfile.write(data[start : end + 1])
                except OSError:  # the reader seeked elsewhere
                    pass

        super().__init__(Handler)
        self.url = f"http://127.0.0.1:{self.port}/"


def closed_port() -> int:
    """A port on 127.0.0.1 that nothing listens on."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class SilentServer:
    """Accepts connections on 127.0.0.1 and never answers (a host that is there but whose service hangs)."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(8)
        self.port = self.sock.getsockname()[1]

    def __enter__(self) -> SilentServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.sock.close()
