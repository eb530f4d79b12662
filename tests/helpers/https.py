"""HTTPS URLs answered by a plain HTTP server on 127.0.0.1, for code that trusts only ``https://`` sources.

Installed as urllib's global opener (what ``urllib.request.urlopen`` uses), so the code under test keeps its real
``https://`` URLs and nothing leaves the machine. huggingface_hub does not go through urllib: Hub files are served
through $HF_ENDPOINT instead.
"""

from __future__ import annotations

import contextlib
import urllib.parse
import urllib.request
from collections.abc import Iterator
from typing import Any


class _ToLocal(urllib.request.BaseHandler):
    handler_order = 100  # before urllib's own HTTPSHandler

    def __init__(self, base: str) -> None:
        self.base = base

    def https_open(self, req: urllib.request.Request) -> Any:
        parts = urllib.parse.urlsplit(req.full_url)
        local = urllib.request.Request(
            self.base + parts.path + (f"?{parts.query}" if parts.query else ""), headers=dict(req.header_items())
        )
        return self.parent.open(local, timeout=req.timeout)  # type: ignore[attr-defined]


@contextlib.contextmanager
def https_served_by(base: str) -> Iterator[None]:
    """Within the block, every ``https://host/path`` that urllib opens is fetched from ``base + /path``."""
    urllib.request.install_opener(urllib.request.build_opener(_ToLocal(base)))
    try:
        yield
    finally:
        urllib.request.install_opener(None)  # type: ignore[arg-type]  # None: urlopen builds its default again
