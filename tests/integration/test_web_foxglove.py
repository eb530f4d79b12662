"""The Foxglove view: a WebSocket client speaking Foxglove's protocol (as the Foxglove app does) subscribes to a
running tiny engine's heads and gets their pictures and detections; nothing is drawn while nobody subscribes."""

from __future__ import annotations

import contextlib
import json
import struct
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from tests_paths import tiny

pytestmark = pytest.mark.timeout(300)


@pytest.fixture
def fed_engine():
    from vpengine.engine import Engine
    from vpengine.io.sources import SyntheticSource

    source = SyntheticSource(160, 120, 30.0, 1 << 30)
    recent: dict[int, np.ndarray] = {}
    stop = threading.Event()
    with Engine(tiny("thread")) as engine:

        def feed() -> None:
            i = 0
            while not stop.wait(1 / 30):
                frame = source.render(i)
                recent[engine.submit(frame)] = frame
                if len(recent) > 32:
                    recent.pop(next(iter(recent)))
                i += 1

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:
            yield engine, recent
        finally:
            stop.set()
            feeder.join(10)


def messages(ws, until: float) -> list:
    """Every message (text as JSON, binary as bytes) until ``until`` (time.monotonic())."""
    import websocket

    out = []
    while time.monotonic() < until:
        ws.settimeout(max(0.05, until - time.monotonic()))
        try:
            op, data = ws.recv_data()
        except websocket.WebSocketTimeoutException:
            break
        out.append(json.loads(data) if op == websocket.ABNF.OPCODE_TEXT else bytes(data))
    return out


@contextlib.contextmanager
def view_socket(fox) -> Iterator[Any]:
    """A WebSocket to the Foxglove view, as the Foxglove app opens one."""
    import websocket

    ws = websocket.create_connection(fox.url, subprotocols=["foxglove.sdk.v1"], timeout=10)
    try:
        yield ws
    finally:
        ws.close()


def advertised(ws) -> dict[str, dict]:
    """The channels the server advertises on connecting, by topic."""
    return {
        c["topic"]: c
        for m in messages(ws, time.monotonic() + 2)
        if isinstance(m, dict) and m.get("op") == "advertise"
        for c in m["channels"]
    }


def subscribe(ws, channels: dict[str, dict], topics: list[str], seconds: float = 3.0) -> dict[str, list[bytes]]:
    """Subscribe to ``topics`` and collect each one's message payloads for ``seconds``."""
    subs = dict(enumerate(topics, 1))
    ws.send(
        json.dumps(
            {"op": "subscribe", "subscriptions": [{"id": i, "channelId": channels[t]["id"]} for i, t in subs.items()]}
        )
    )
    got: dict[str, list[bytes]] = {t: [] for t in topics}
    for m in messages(ws, time.monotonic() + seconds):
        if isinstance(m, bytes) and m[0] == 1:  # message data: opcode, subscription id, log time, payload
            sub, _log_time = struct.unpack_from("<IQ", m, 1)
            got[subs[sub]].append(m[13:])
    return got


def test_foxglove_gets_each_heads_picture_and_the_detections_only_while_subscribed(fed_engine):
    from vpengine.web.foxglove import FoxgloveView

    engine, recent = fed_engine
    with FoxgloveView(engine, port=0, frames=recent.get, hz=20) as fox, view_socket(fox) as ws:
        channels = advertised(ws)
        assert {
            "/vpengine/depth/image",
            "/vpengine/seg/image",
            "/vpengine/det/image",
            "/vpengine/det/annotations",
        } <= set(channels)
        assert channels["/vpengine/det/image"]["schemaName"] == "foxglove.CompressedImage"
        assert channels["/vpengine/det/annotations"]["schemaName"] == "foxglove.ImageAnnotations"
        assert fox.pictures.made == 0 and fox.sent == 0  # nobody subscribed: nothing drawn
        got = subscribe(ws, channels, ["/vpengine/seg/image", "/vpengine/det/annotations"])
        assert len(got["/vpengine/seg/image"]) >= 5
        assert all(b"\xff\xd8\xff" in p and b"jpeg" in p for p in got["/vpengine/seg/image"])  # a JPEG inside
        assert got["/vpengine/det/annotations"] and all(b"class_" in p for p in got["/vpengine/det/annotations"])
        assert {h for _, h in fox._sent} == {"seg", "det"}  # depth: nobody subscribed, never drawn


def test_with_several_cameras_each_camera_has_its_own_channels_and_pictures():
    from vpengine.engine import Engine
    from vpengine.io.sources import SyntheticSource
    from vpengine.web.foxglove import FoxgloveView

    sizes = {"front": (160, 120), "rear": (200, 90)}
    cfg = tiny("thread", "cameras=[{name: front}, {name: rear}]", "heads.det.cameras=[front]")
    with Engine(cfg) as engine:
        recent: dict[int, np.ndarray] = {}
        for i in range(3):
            for camera, (w, h) in sizes.items():
                frame = SyntheticSource(w, h, 30.0, 10).render(i)
                fid = engine.submit(frame, camera=camera)
                recent[fid] = frame
                engine.wait(fid, timeout=20)
        with FoxgloveView(engine, port=0, frames=recent.get, hz=20) as fox, view_socket(fox) as ws:
            channels = advertised(ws)
            assert {
                "/vpengine/front/seg/image",
                "/vpengine/rear/seg/image",
                "/vpengine/front/det/annotations",
            } <= set(channels)
            assert "/vpengine/rear/det/image" not in channels and "/vpengine/seg/image" not in channels
            got = subscribe(ws, channels, ["/vpengine/front/seg/image", "/vpengine/rear/seg/image"])
            # each channel gets its own camera's picture, named by its frame_id
            assert got["/vpengine/front/seg/image"] and all(b"front" in p for p in got["/vpengine/front/seg/image"])
            assert got["/vpengine/rear/seg/image"] and all(b"rear" in p for p in got["/vpengine/rear/seg/image"])
            assert {k for k in fox._sent} == {("front", "seg"), ("rear", "seg")}
