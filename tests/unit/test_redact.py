"""Note [Redacting] (vpengine/redact.py): no password, token or key of a stream URL or a pipeline gets into a message,
a log or summary.json."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from vpengine.redact import redact


@pytest.mark.parametrize(
    ("text", "shown"),
    [
        ("rtsp://admin:secret@cam:554/stream", "rtsp://admin:***@cam:554/stream"),
        # FFmpeg splits the authority at its last '@': the password is 'p@ss'
        ("rtsp://admin:p@ss@cam/stream", "rtsp://admin:***@cam/stream"),
        ("rtsp://admin:p@s@s@10.0.0.2/h264", "rtsp://admin:***@10.0.0.2/h264"),
        # a password with a '/' in it, and with both
        ("rtsp://admin:pa/ss@cam/stream", "rtsp://admin:***@cam/stream"),
        ("rtsp://admin:p@s/s@cam/stream", "rtsp://admin:***@cam/stream"),
        ("rtsp://admin:1234/5@cam/stream", "rtsp://admin:***@cam/stream"),
        # a token as the user, and an empty user
        ("https://ghp_abc123@example.com/x.pt", "https://***@example.com/x.pt"),
        ("rtsp://:secret@cam/", "rtsp://:***@cam/"),
        # credentials in the query, as IP cameras take them
        (
            "http://cam/video.cgi?user=admin&password=secret&res=hd",
            "http://cam/video.cgi?user=admin&password=***&res=hd",
        ),
        ("http://cam/videostream.cgi?user=admin&pwd=s3cr%2Ft", "http://cam/videostream.cgi?user=admin&pwd=***"),
        ("rtsp://cam/live?passwd=x&channel=1", "rtsp://cam/live?passwd=***&channel=1"),
        ("https://cam/api?token=abc.def#frag", "https://cam/api?token=***#frag"),
        ("https://cam/api?KEY=abc", "https://cam/api?KEY=***"),
        (
            "https://b.s3.amazonaws.com/w.pt?X-Amz-Signature=ab12&X-Amz-Expires=60",
            "https://b.s3.amazonaws.com/w.pt?X-Amz-Signature=***&X-Amz-Expires=60",
        ),
        ("https://host/x?api_key=1&access_token=2", "https://host/x?api_key=***&access_token=***"),
        # both at once
        ("rtsp://u:p@cam/s?token=t", "rtsp://u:***@cam/s?token=***"),
    ],
)
def test_urls_lose_their_passwords_and_secret_query_values(text, shown):
    assert redact(text) == shown
    assert redact(shown) == shown  # idempotent: redacting twice changes nothing


def test_urls_anywhere_in_a_message_or_a_pipeline_are_redacted():
    pipeline = (
        "rtspsrc location=rtsp://admin:p@ss@10.0.0.2:554/h264 latency=0 user-id=admin user-pw=hunter2 "
        'proxy-pw="a b" ! rtph264depay ! h264parse ! avdec_h264 ! videoconvert ! appsink'
    )
    assert redact(pipeline) == (
        "rtspsrc location=rtsp://admin:***@10.0.0.2:554/h264 latency=0 user-id=admin user-pw=*** "
        "proxy-pw=*** ! rtph264depay ! h264parse ! avdec_h264 ! videoconvert ! appsink"
    )
    msg = "cannot open stream 'rtsp://a:b@h/x': refused; pipeline \"uridecodebin uri=http://u:v@h\""
    assert redact(msg) == "cannot open stream 'rtsp://a:***@h/x': refused; pipeline \"uridecodebin uri=http://u:***@h\""


@pytest.mark.parametrize(
    "text",
    [
        "rtsp://cam:554/stream",
        "http://host/users/@me/feed",
        "https://example.com/a?x=1&keyframes=2&monkey=3&bypass=4",
        "videotestsrc ! x264enc key-int-max=30 ! appsink",
        "/dev/video0",
        "camera:0",
        "gst:videotestsrc ! appsink",
        "video '/data/run@2/clip.mp4'",
        "",
    ],
)
def test_text_without_secrets_comes_back_as_it_is(text):
    assert redact(text) == text


def test_the_module_imports_nothing_of_vpengine():
    source = Path(__import__("vpengine.redact").redact.__file__).read_text()
    imported = [
        n.module if isinstance(n, ast.ImportFrom) else a.name
        for n in ast.walk(ast.parse(source))
        if isinstance(n, (ast.Import, ast.ImportFrom))
        for a in (n.names if isinstance(n, ast.Import) else [n])
    ]
    assert not [m for m in imported if m and m.split(".")[0] == "vpengine"]
