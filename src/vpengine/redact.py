"""Secrets out of text that goes to a terminal, a log or a file: :func:`redact`.

Note [Redacting]
~~~~~~~~~~~~~~~~
Stream URLs and GStreamer pipelines carry credentials in three places, and all three reach messages, logs and
summary.json unless redacted:

- a URL's userinfo, ``rtsp://admin:secret@cam/stream``. FFmpeg ends the authority at the first ``/``, ``?`` or ``#``
  and splits it at its LAST ``@``, so ``rtsp://admin:p@ss@cam/`` is user ``admin``, password ``p@ss``; a password
  typed with a ``/`` in it (``admin:pa/ss@cam``) ends FFmpeg's authority early but is a password all the same. So
  the userinfo runs to the last ``@`` before the query when the authority holds an ``@``, or a ``:`` and an ``@``
  follows. This errs toward hiding: a URL with a port and an ``@`` in its path (``http://host:80/a/@b``) shows as
  ``http://host:***@b``. The user name stays (``admin:***@``); userinfo without a ``:`` is a token used as the
  user (``https://TOKEN@host/``) and goes whole (``***@``).
- a query value, ``?user=admin&password=secret`` (``pwd``, ``passwd``, ``token``, ``key``, ``sig``... as IP
  cameras and signed download links name them).
- a pipeline property, ``rtspsrc user-id=admin user-pw=secret`` (``proxy-pw``), with or without quotes.

This module imports nothing of vpengine, so anything (sources, downloads) can use it.
"""

from __future__ import annotations

import re

__all__ = ["redact"]

MASK = "***"

# a URL up to whatever ends a word of text: whitespace, a quote, angle brackets
_URL = re.compile(r"(?<![A-Za-z0-9+.-])([A-Za-z][A-Za-z0-9+.-]*://)([^\s'\"<>]*)")
_SECRET_WORDS = (
    "password|passwd|passwort|passphrase|pwd|pw|pass|token|accesstoken|secret|key|apikey|signature|sig|auth"
    "|authorization|credentials?"
)
# a key that is a secret word, or ends in one after a separator (user-pw, api_key, X-Amz-Signature), then its value:
# quoted, or up to what ends a query value or a pipeline property
_SECRET = re.compile(rf"(?i)(?<![\w.-])((?:[\w.-]*[-_.])?(?:{_SECRET_WORDS})\s*=\s*)(\"[^\"]*\"|'[^']*'|[^&#\s'\"]+)")


def redact(text: str) -> str:
    """``text`` with every URL's userinfo password (``rtsp://user:***@host/``) and every secret-looking query value
    or property (``?password=***``, ``user-pw=***``) masked (Note [Redacting]). Idempotent; text without secrets
    comes back as it is."""
    return _SECRET.sub(lambda m: m.group(1) + MASK, _URL.sub(_redact_url, text))


def _redact_url(m: re.Match[str]) -> str:
    scheme, rest = m.group(1), m.group(2)
    query = len(rest)
    for c in "?#":
        i = rest.find(c)
        if i >= 0:
            query = min(query, i)
    head, tail = rest[:query], rest[query:]
    slash = head.find("/")
    authority = head if slash < 0 else head[:slash]
    if "@" not in authority and not (":" in authority and "@" in head[len(authority) :]):
        return m.group(0)
    at = head.rindex("@")
    userinfo, host = head[:at], head[at + 1 :]
    masked = f"{userinfo.split(':', 1)[0]}:{MASK}" if ":" in userinfo else MASK
    return f"{scheme}{masked}@{host}{tail}"
