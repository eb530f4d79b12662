"""The live view's server, pictures and metrics against a stand-in engine (real HTTP on 127.0.0.1, no processes)."""

from __future__ import annotations

import json
import math
import threading
import urllib.error
import urllib.request
from types import SimpleNamespace

import numpy as np
import pytest

from vpengine import checks
from vpengine.cli.serve import parse_address
from vpengine.engine.boundary import Boundary
from vpengine.engine.results import Result
from vpengine.visualize import colorize_depth, overlay_segmentation
from vpengine.web import WebServer
from vpengine.web.pictures import Pictures, render
from vpengine.web.server import is_loopback, parse_priority, parse_rate

H, W = 60, 80
INFOS = {
    "depth": {"kind": "depth"},
    "seg": {"kind": "segmentation", "labels": ["a", "b", "c"]},
    "det": {"kind": "detection", "labels": ["car", "person"]},
}


def model_stats(runs: int, target: float | None) -> dict:
    nan = {"p50": math.nan, "p90": math.nan, "p99": math.nan, "mean": math.nan}
    lat = {"p50": 4.0, "p90": 5.0, "p99": 9.0, "mean": 4.5} if runs else nan
    return {
        "state": "running",
        "target_hz": target,
        "achieved_hz": 12.5 if runs else 0.0,
        "runs": runs,
        "skipped": 3,
        "dropped": 1,
        "errors": 0,
        "restarts": 2,
        "latency_ms": lat,
        "e2e_latency_ms": lat,
        "device_mem_bytes": 5e6,
        "last_error": None,
    }


class DoorOut(Boundary):
    """The engine's door out (``Boundary.to_frame``, the real one) with the kinds the engine's boundary works out for
    these heads (Note [Frame grid]) and the heads that keep the canvas grid (``native``); no door in."""

    def __init__(self, native: tuple[str, ...] = ()) -> None:
        kinds = {"depth": "map", "depth_color": "map", "classes": "labels", "boxes": "boxes"}
        self.kinds = dict.fromkeys(INFOS, kinds)  # type: ignore[arg-type]
        self.native = set(native)


class StandIn:
    """What the view uses of an Engine: stats, set_rate/rate, set_priority, latest, head_info, cameras, config,
    boundary, running.
    ``results``: head -> its newest result; ``camera_results``, with several ``cameras``: (camera, head) -> it."""

    def __init__(self, cameras: tuple[str, ...] = ("camera",), served: dict[str, list[str]] | None = None) -> None:
        self.running = True
        self.cameras = list(cameras)
        served = served or {}
        self.lanes = SimpleNamespace(served=lambda head: served.get(head, list(self.cameras)))
        self.boundary = DoorOut()
        self.rates: dict[str, float | None] = {"foundation": None, "depth": None, "seg": 5.0, "det": 0.0}
        self.results: dict[str, Result | None] = dict.fromkeys(INFOS)
        #: (head or None for the camera's own, camera or None for all) -> priority, as set_priority was called
        self.priorities: dict[tuple[str | None, str | None], int] = {}
        self.camera_results: dict[tuple[str, str], Result] = {}
        self.latest_calls = 0
        self.lock = threading.Lock()

    def stats(self) -> dict:
        models = {n: model_stats(0 if n == "det" else 100, r) for n, r in self.rates.items()}
        return {
            "engine": {
                "state": "running",
                "mode": "thread",
                "device": "cpu",
                "uptime_s": 1.0,
                "submitted": 120,
                "rejected": 1,
            },
            "models": models,
            "results": {h: {"missed": 7} for h in INFOS},
            "memory": {"mailbox_host_bytes": 1000, "mailbox_device_bytes": 0},
        }

    def set_rate(self, model: str, hz: float | None) -> None:
        if model not in self.rates:
            raise KeyError(f"no model named {model!r}; models: {list(self.rates)}")
        self.rates[model] = checks.rate(model, hz)

    def rate(self, model: str) -> float | None:
        return self.rates[model]

    def set_priority(self, head: str | None, priority: int, camera: str | None = None) -> None:
        value = checks.priority(priority)  # Engine.set_priority's errors: KeyError for a head, else ValueError
        if head is not None and head not in INFOS:
            raise KeyError(f"no head named {head!r}; heads: {list(INFOS)}")
        if camera not in (None, *self.cameras) or (head is None and camera is None):
            raise ValueError(f"camera must be one of {self.cameras}, got {camera!r}")
        self.priorities[(head, camera)] = value

    def head_info(self, head: str) -> dict:
        if head not in INFOS:
            raise KeyError(f"no head named {head!r}; heads: {list(INFOS)}")
        return dict(INFOS[head])

    def latest(self, head: str, copy: bool = True, camera: str | None = None) -> Result | None:
        with self.lock:
            self.latest_calls += 1
        self.head_info(head)
        if len(self.cameras) > 1 and camera is not None:
            return self.camera_results.get((camera, head))
        return self.results[head]


def result(head: str, frame_id: int, seq: int, outputs: dict, frame_size: tuple[int, int] = (H, W)) -> Result:
    return Result(head, frame_id, 1.7e9 + frame_id, 0.012, outputs, seq, frame_size=frame_size)


def seg_result(frame_id: int = 7, seq: int = 1) -> Result:
    classes = np.zeros((H, W), np.uint8)
    classes[:, W // 2 :] = 2
    return result("seg", frame_id, seq, {"classes": classes})


def det_result(frame_id: int = 7, seq: int = 1) -> Result:
    boxes = np.array([[10, 10, 40, 30]], np.float32)
    return result(
        "det",
        frame_id,
        seq,
        {"boxes": boxes, "scores": np.array([0.9], np.float32), "labels": np.array([1], np.int32), "count": 1},
    )


def frame_of(value: int) -> np.ndarray:
    return np.full((H, W, 3), value, np.uint8)


def request(url: str, method: str = "GET", body: bytes | None = None, headers: dict | None = None):
    """(status, headers, body) of one request, errors included."""
    req = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, r.headers, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers, e.read()


@pytest.fixture
def engine():
    return StandIn()


@pytest.fixture
def view(engine):
    frames = {7: frame_of(200), 8: frame_of(30)}
    with WebServer(engine, "127.0.0.1", 0, frames=frames.get) as v:
        yield v


# ------------------------------------------------------------------------------------------------ parsing
@pytest.mark.parametrize(
    ("body", "hz"), [(b'{"hz": 5}', 5.0), (b'{"hz": 0}', 0.0), (b'{"hz": null}', None), (b'{"hz": 2.5}', 2.5)]
)
def test_a_rate_body_is_a_number_zero_or_null(body, hz):
    assert parse_rate(body, "seg") == hz


@pytest.mark.parametrize(
    ("body", "why"),
    [
        (b"", "the body is empty"),
        (b"null", "got null"),
        (b"5", "got 5"),
        (b'{"rate": 5}', 'got {"rate": 5}'),
        (b"{nope", "not JSON"),
    ],
)
def test_a_bad_rate_body_says_what_is_accepted(body, why):
    with pytest.raises(ValueError, match="a number from 0 to 10000") as e:
        parse_rate(body, "seg")
    assert why in str(e.value)


@pytest.mark.parametrize(
    ("body", "why"),
    [
        (b'{"hz": "5"}', 'got "5"'),
        (b'{"hz": true}', "got true"),
        (b'{"hz": NaN}', "got NaN"),
        (b'{"hz": -1}', "got -1"),
        (b'{"hz": 20000}', "got 20000"),
    ],
)
def test_a_bad_rate_gets_the_one_rate_message(body, why):
    with pytest.raises(
        ValueError, match=r"rate for 'seg' must be null \(no limit\) or a number of Hz from 0 to 10000"
    ) as e:
        parse_rate(body, "seg")
    assert why in str(e.value)


def test_a_priority_body_is_an_integer_in_range_and_a_bad_one_says_what_is_accepted():
    assert parse_priority(b'{"priority": 10}') == 10 and parse_priority(b'{"priority": -100}') == -100
    for body, why in (
        (b"", "the body is empty"),
        (b"7", "got 7"),
        (b"{nope", "not JSON"),
        (b'{"prio": 7}', 'got {"prio": 7}'),
    ):
        with pytest.raises(ValueError, match=r'\{"priority": P\} with P an integer from -100 to 100') as e:
            parse_priority(body)
        assert why in str(e.value)
    for body, why in (
        (b'{"priority": 101}', "101"),
        (b'{"priority": 1.5}', "1.5"),
        (b'{"priority": "7"}', '"7"'),
        (b'{"priority": null}', "null"),
    ):
        with pytest.raises(ValueError, match=f"priority must be an integer from -100 to 100.*got {why}"):
            parse_priority(body)


@pytest.mark.parametrize(
    ("text", "address"),
    [
        ("8080", ("127.0.0.1", 8080)),
        ("0.0.0.0:9000", ("0.0.0.0", 9000)),
        ("[::1]:81", ("::1", 81)),
        ("robot.local:0", ("robot.local", 0)),
        (":8080", ("127.0.0.1", 8080)),
    ],
)
def test_serve_addresses(text, address):
    assert parse_address(text) == address


@pytest.mark.parametrize("text", ["", "x", "host:", "1:2:3", "70000", "-1"])
def test_bad_serve_addresses_are_refused_with_the_accepted_form(text):
    with pytest.raises(ValueError, match=r"\[HOST:\]PORT|brackets"):
        parse_address(text)


def test_loopback_names_and_addresses():
    assert all(map(is_loopback, ["127.0.0.1", "127.3.2.1", "::1", "[::1]", "localhost"]))
    assert not any(map(is_loopback, ["0.0.0.0", "::", "192.168.1.5", "robot.local", ""]))


# -------------------------------------------------------------------------------------------------- routes
def test_stats_are_the_engines_as_json_with_nan_as_null(view, engine):
    status, headers, body = request(view.url + "api/stats")
    assert status == 200 and headers["Content-Type"] == "application/json"
    doc = json.loads(body)
    assert doc["models"]["seg"]["target_hz"] == 5.0 and doc["models"]["depth"]["runs"] == 100
    assert doc["models"]["det"]["latency_ms"]["p50"] is None  # NaN: no runs yet


def test_the_page_is_one_self_contained_document(view):
    status, headers, body = request(view.url)
    assert status == 200 and headers["Content-Type"].startswith("text/html")
    page = body.decode()
    assert "/api/stats" in page and "/api/rate/" in page and "/api/priority/" in page and "/api/latest/" in page
    assert "__STATS_MS__" not in page and "const STATS_MS = 500, PICTURE_MS = 250" in page
    assert "http://" not in page and "https://" not in page  # nothing from the internet (no CDN)


def test_put_rate_sets_it_and_answers_the_rate_now(view, engine):
    for body, want in ((b'{"hz": 7}', 7.0), (b'{"hz": null}', None), (b'{"hz": 0}', 0.0)):
        status, _, reply = request(view.url + "api/rate/depth", "PUT", body)
        assert status == 200 and json.loads(reply) == {"model": "depth", "hz": want}
        assert engine.rates["depth"] == want


@pytest.mark.parametrize(
    ("model", "body", "reason"),
    [
        ("depth", b'{"hz": -2}', "from 0 to 10000 (0 pauses), got -2"),
        ("nope", b'{"hz": 1}', "no model named 'nope'"),
        ("depth", b'{"hz": "fast"}', 'got "fast"'),
        ("depth", b"", "the body is empty"),
        ("depth", b'{"hz": 5, "x": 1}', '"x" is no field of this body'),
    ],
)
def test_a_bad_rate_or_model_is_a_400_with_the_reason(view, engine, model, body, reason):
    status, _, reply = request(view.url + f"api/rate/{model}", "PUT", body)
    assert status == 400 and reason in json.loads(reply)["error"]
    assert engine.rates["depth"] is None  # unchanged


def test_put_priority_sets_a_heads_a_lanes_or_a_cameras_and_answers_it(view, engine):
    for key, body, want in (
        ("depth", b'{"priority": 10}', ("depth", None, 10)),
        ("seg@camera", b'{"priority": -3}', ("seg", "camera", -3)),
        ("%40camera", b'{"priority": 4}', (None, "camera", 4)),  # @camera, quoted as the page's encodeURIComponent
    ):
        status, _, reply = request(view.url + f"api/priority/{key}", "PUT", body)
        assert status == 200 and json.loads(reply) == dict(zip(("head", "camera", "priority"), want))
        assert engine.priorities[want[:2]] == want[2]


@pytest.mark.parametrize(
    ("key", "body", "status", "reason"),
    [
        ("depth", b'{"priority": 101}', 400, "from -100 to 100 (higher: more important), got 101"),
        ("depth", b'{"priority": 2.5}', 400, "got 2.5"),
        ("depth", b'{"priority": "high"}', 400, 'got "high"'),
        ("depth", b'{"priority": null}', 400, "got null"),
        ("depth", b'{"priority": 3, "prio": 4}', 400, '"prio" is no field of this body'),
        ("", b'{"priority": 3}', 400, "the priority's key is empty; give HEAD, HEAD@CAMERA or @CAMERA"),
        ("depth", b"", 400, "the body is empty"),
        ("depth@nocam", b'{"priority": 1}', 400, "got 'nocam'"),
        ("nope", b'{"priority": 1}', 404, "no head named 'nope'"),
    ],
)
def test_a_bad_priority_is_a_400_and_an_unknown_head_a_404_with_the_reason(view, engine, key, body, status, reason):
    got, _, reply = request(view.url + f"api/priority/{key}", "PUT", body)
    assert got == status and reason in json.loads(reply)["error"]
    assert engine.priorities == {}  # unchanged


def test_wrong_methods_unknown_paths_and_large_bodies_are_refused(view):
    assert request(view.url + "api/rate/depth")[0] == 405
    assert request(view.url + "api/priority/depth")[0] == 405
    assert request(view.url + "api/stats", "PUT", b"{}")[0] == 405
    status, _, body = request(view.url + "api")
    assert status == 404 and json.loads(body)["error"].startswith("no such page: /api; the pages: GET / (the live")
    assert "/api/stats" in json.loads(body)["error"]
    assert request(view.url + "api/rate/depth", "PUT", b"x" * 10000)[0] == 413


def test_a_picture_is_drawn_on_the_results_own_frame(view, engine):
    engine.results["seg"] = seg_result(frame_id=7)
    status, headers, body = request(view.url + "api/latest/seg.jpg")
    assert status == 200 and headers["Content-Type"] == "image/jpeg"
    assert headers["X-Frame-Id"] == "7" and headers["X-On-Frame"] == "1" and headers["X-Latency-Ms"] == "12.00"
    import cv2

    got = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR).astype(int)
    want = overlay_segmentation(frame_of(200), engine.results["seg"]["classes"]).astype(int)
    assert np.abs(got - want).mean() < 3  # JPEG, not exact
    other = overlay_segmentation(frame_of(30), engine.results["seg"]["classes"]).astype(int)
    assert np.abs(got - other).mean() > 30  # frame 8's picture would look different


def test_without_its_frame_a_picture_shows_the_outputs_alone(engine):
    frames = {8: frame_of(30)}  # the newest frame, but not the result's
    pictures = Pictures(frames.get)
    engine.results["det"] = det_result(frame_id=7)
    pic = pictures.latest(engine, "det")
    assert pic is not None and not pic.on_frame and pic.frame_id == 7
    import cv2

    img = cv2.imdecode(np.frombuffer(pic.jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (H, W, 3)
    assert np.abs(img.astype(int)[40:, 50:] - 24).max() < 12  # the dark canvas, not frame 8 (value 30 + boxes)


def test_a_picture_is_drawn_at_the_results_frame_size_not_the_inputs():
    """Note [Pictures and frames]: a camera of another size than the config's input gets its overlay on its frame."""
    import cv2

    fh, fw = 90, 200  # the frame's size; the stand-in engine's input is H x W
    big = np.full((fh, fw, 3), 200, np.uint8)
    pictures = Pictures({7: big}.get)
    classes = np.zeros((fh, fw), np.uint8)
    classes[:, fw // 2 :] = 2
    engine = StandIn()
    engine.results["seg"] = result("seg", 7, 1, {"classes": classes}, frame_size=(fh, fw))
    pic = pictures.latest(engine, "seg", width=fw)
    assert pic is not None and pic.on_frame and pic.width == fw
    got = cv2.imdecode(np.frombuffer(pic.jpeg, np.uint8), cv2.IMREAD_COLOR).astype(int)
    assert np.abs(got - overlay_segmentation(big, classes).astype(int)).mean() < 3
    boxes = np.array([[150, 60, 190, 85]], np.float32)  # beyond the input's 80 x 60: in the frame's pixels
    engine.results["det"] = result("det", 7, 1, {"boxes": boxes, "scores": np.array([0.9], np.float32),
                                                  "labels": np.array([1], np.int32)}, frame_size=(fh, fw))  # fmt: skip
    pic = pictures.latest(engine, "det", width=fw)
    assert pic is not None and pic.on_frame
    got = cv2.imdecode(np.frombuffer(pic.jpeg, np.uint8), cv2.IMREAD_COLOR).astype(int)
    assert np.abs(got[62:84, 152:188] - 200).mean() < 3  # inside the box: the frame
    assert np.abs(got[60, 152:188] - 200).max() > 60  # its top edge drawn where the box is


def test_a_native_grid_picture_is_mapped_to_its_frame():
    from vpengine.engine.boundary import Placement

    fh, fw = 30, 80  # letterboxed into the 60 x 80 canvas: rows 15..45
    placement = Placement.fit((fh, fw), (H, W))
    classes = np.zeros((H, W), np.uint8)
    classes[placement.y0 : placement.y0 + fh] = 2  # the frame's region is class 2, the bands class 0
    r = result("seg", 7, 1, {"classes": classes}, frame_size=(fh, fw))
    r.grid, r.placement = "native", placement
    engine = StandIn()
    engine.boundary = DoorOut(native=("seg",))
    engine.results["seg"] = r
    frame = np.full((fh, fw, 3), 100, np.uint8)
    pic = Pictures({7: frame}.get).latest(engine, "seg", width=fw)
    assert pic is not None and pic.on_frame and pic.width == fw
    import cv2

    got = cv2.imdecode(np.frombuffer(pic.jpeg, np.uint8), cv2.IMREAD_COLOR).astype(int)
    want = overlay_segmentation(frame, np.full((fh, fw), 2, np.uint8)).astype(int)
    assert got.shape == (fh, fw, 3) and np.abs(got - want).mean() < 3


def test_pictures_of_every_kind_render_at_the_width_asked():
    frame = frame_of(90)
    depth = np.linspace(0, 1, H * W, dtype=np.float32).reshape(H, W)
    info = {**INFOS["det"], "frame_size": (H, W)}
    assert render(INFOS["depth"], {"depth": depth}, None, W).tolist() == colorize_depth(depth).tolist()
    assert render(INFOS["depth"], {"depth": depth}, None, 40).shape == (30, 40, 3)
    assert render(INFOS["seg"], seg_result().outputs, frame, 40).shape == (30, 40, 3)
    assert render(info, det_result().outputs, frame, 40).shape == (30, 40, 3)
    assert render(info, det_result().outputs, None, 200).shape == (H, W, 3)  # never enlarged
    assert render({"kind": "generic"}, {"x": depth}, frame) is None


def test_with_several_cameras_each_camera_has_its_own_picture_of_each_head():
    """The newest picture per (camera, head), not the newest of any camera's: ?camera= picks, default the first
    camera the head serves; an unknown camera is a 400 naming the cameras."""
    engine = StandIn(("front", "rear"), served={"det": ["rear"]})
    frames = {7: frame_of(200), 8: frame_of(30)}
    engine.camera_results[("front", "seg")] = seg_result(frame_id=7, seq=1)
    engine.camera_results[("rear", "seg")] = seg_result(frame_id=8, seq=2)  # the newest of any camera's
    engine.camera_results[("rear", "det")] = det_result(frame_id=8, seq=1)
    with WebServer(engine, "127.0.0.1", 0, frames=frames.get) as v:
        for query, camera, fid in (("", "front", "7"), ("?camera=front", "front", "7"), ("?camera=rear", "rear", "8")):
            status, headers, _ = request(v.url + "api/latest/seg.jpg" + query)
            assert status == 200 and (headers["X-Camera"], headers["X-Frame-Id"]) == (camera, fid), query
        status, headers, _ = request(v.url + "api/latest/det.jpg")  # det serves the rear camera alone
        assert status == 200 and (headers["X-Camera"], headers["X-Frame-Id"]) == ("rear", "8")
        status, _, body = request(v.url + "api/latest/seg.jpg?camera=side")
        assert status == 400 and json.loads(body)["error"] == "no camera named 'side'; cameras: ['front', 'rear']"
        status, _, body = request(v.url + "api/latest/det.jpg?camera=front")
        assert status == 404 and "'det' serves cameras ['rear'], not 'front'" in json.loads(body)["error"]
        assert request(v.url + "api/latest/depth.jpg?camera=rear")[0] == 204


def test_no_result_yet_is_204_and_an_unknown_head_404(view, engine):
    assert request(view.url + "api/latest/depth.jpg")[0] == 204
    status, _, body = request(view.url + "api/latest/nope.jpg")
    assert status == 404 and "no head named 'nope'" in json.loads(body)["error"]
    assert request(view.url + "api/latest/seg.jpg?width=3")[0] == 400


def test_pictures_are_made_only_when_asked_and_at_most_max_hz_per_head(engine):
    pictures = Pictures(max_hz=1e9)
    engine.results["seg"] = seg_result(seq=1)
    assert engine.latest_calls == 0  # nobody looked: nothing ran
    first = pictures.latest(engine, "seg")
    assert pictures.latest(engine, "seg") is first and pictures.made == 1  # same result: drawn once
    engine.results["seg"] = seg_result(frame_id=8, seq=2)
    assert pictures.latest(engine, "seg").frame_id == 8 and pictures.made == 2
    slow = Pictures(max_hz=0.01)
    engine.results["seg"] = seg_result(seq=3)
    slow.latest(engine, "seg")
    engine.results["seg"] = seg_result(frame_id=9, seq=4)
    assert slow.latest(engine, "seg").frame_id == 7 and slow.made == 1  # within 1 / max_hz: served again


def test_engine_not_running_is_503(engine):
    with WebServer(lambda: None, "127.0.0.1", 0) as v:
        status, _, body = request(v.url + "api/stats")
        assert status == 503 and "not started yet" in json.loads(body)["error"]
        assert b"vpengine_up 0.0" in request(v.url + "metrics")[2]
    engine.running = False
    with WebServer(engine, "127.0.0.1", 0) as v:
        assert request(v.url + "api/rate/depth", "PUT", b'{"hz": 1}')[0] == 503
        assert request(v.url + "api/priority/depth", "PUT", b'{"priority": 1}')[0] == 503


# ------------------------------------------------------------------------------------------------- access
def test_beyond_loopback_a_token_is_required_at_start(engine):
    with pytest.raises(ValueError, match="reaches beyond this machine: give a token"):
        WebServer(engine, "0.0.0.0", 0)


def test_with_a_token_every_request_carries_it(engine):
    with WebServer(engine, "0.0.0.0", 0, token="s3cret") as v:
        status, headers, _ = request(v.url + "api/stats")
        assert status == 401 and headers["WWW-Authenticate"] == "Bearer"
        assert request(v.url + "api/rate/depth", "PUT", b'{"hz": 1}')[0] == 401
        assert request(v.url + "metrics", headers={"Authorization": "Bearer wrong"})[0] == 401
        assert request(v.url)[0] == 200  # the page holds no data: it says what is missing
        assert engine.rates["depth"] is None
        assert request(v.url + "api/stats", headers={"Authorization": "Bearer s3cret"})[0] == 200
        assert request(v.url + "metrics?token=s3cret")[0] == 200
        status, _, _ = request(v.url + "api/rate/depth", "PUT", b'{"hz": 1}', {"Authorization": "Bearer s3cret"})
        assert status == 200 and engine.rates["depth"] == 1.0


def test_on_loopback_a_request_must_name_a_loopback_host(view):
    assert request(view.url + "api/stats", headers={"Host": "evil.example:80"})[0] == 403
    assert request(view.url + "api/stats", headers={"Host": f"localhost:{view.port}"})[0] == 200


def test_stop_returns_and_closes_idle_connections(engine):
    import http.client

    v = WebServer(engine, "127.0.0.1", 0)
    conn = http.client.HTTPConnection("127.0.0.1", v.port, timeout=10)
    conn.request("GET", "/api/stats")
    assert conn.getresponse().read()  # the connection stays open (keep-alive)
    v.stop()
    v.stop()
    with pytest.raises(OSError):
        request(v.url + "api/stats")


# ------------------------------------------------------------------------------------------------ metrics
def test_metrics_are_prometheus_text_with_vpengine_names_and_a_model_label(view):
    from prometheus_client.parser import text_string_to_metric_families

    status, headers, body = request(view.url + "metrics")
    assert status == 200 and headers["Content-Type"].startswith("text/plain; version=")
    fams = {f.name: f for f in text_string_to_metric_families(body.decode())}
    assert all(name.startswith("vpengine_") for name in fams)

    def value(name, suffix="", **labels):
        (s,) = [s for s in fams[name].samples if s.name == name + suffix and s.labels == labels]
        return s.value

    for name in ("runs", "skipped", "dropped", "errors", "restarts"):
        assert fams[f"vpengine_{name}"].type == "counter"
    assert value("vpengine_runs", "_total", model="depth") == 100
    assert value("vpengine_restarts", "_total", model="seg") == 2
    assert value("vpengine_target_hz", model="seg") == 5.0
    assert value("vpengine_target_hz", model="depth") == math.inf  # unlimited
    assert value("vpengine_target_hz", model="det") == 0.0  # paused
    assert value("vpengine_achieved_hz", model="depth") == 12.5
    assert value("vpengine_device_memory_bytes", model="depth") == 5e6
    assert fams["vpengine_latency_seconds"].type == "summary"
    assert value("vpengine_latency_seconds", model="depth", quantile="0.99") == pytest.approx(0.009)
    assert value("vpengine_latency_seconds", "_count", model="depth") == 100
    assert not [
        s for s in fams["vpengine_latency_seconds"].samples if s.labels.get("model") == "det" and "quantile" in s.labels
    ]  # no runs: no quantiles (not NaN)
    assert value("vpengine_results_missed", "_total", model="seg") == 7
    assert value("vpengine_frames_submitted", "_total") == 120
    assert value("vpengine_up") == 1


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int32, np.int64])
def test_class_maps_of_any_integer_type_shrink_to_class_ids_they_had(dtype):
    classes = (np.arange(H * W).reshape(H, W) % 5).astype(dtype)
    pic = render(INFOS["seg"], {"classes": classes}, None, 40)
    assert pic.shape == (30, 40, 3)
    colours = {tuple(c) for c in render(INFOS["seg"], {"classes": classes}, None, W).reshape(-1, 3)}
    assert {tuple(c) for c in pic.reshape(-1, 3)} <= colours


def test_serve_options_from_the_command_line(monkeypatch):
    import argparse

    from vpengine.cli.serve import ServeOptions, add_serve_arguments, serve_options

    p = argparse.ArgumentParser()
    add_serve_arguments(p)
    monkeypatch.delenv("VPENGINE_SERVE_TOKEN", raising=False)
    assert serve_options(p.parse_args([])) is None
    assert serve_options(p.parse_args(["--serve", "8080"])) == ServeOptions(("127.0.0.1", 8080))
    assert serve_options(p.parse_args(["--foxglove", "8765"])) == ServeOptions(None, None, ("127.0.0.1", 8765))
    with pytest.raises(ValueError, match="--serve-token TOKEN or set \\$VPENGINE_SERVE_TOKEN"):
        serve_options(p.parse_args(["--serve", "0.0.0.0:8080"]))
    with pytest.raises(ValueError, match="--foxglove 0.0.0.0:1: Foxglove's WebSocket protocol has no authentication"):
        serve_options(p.parse_args(["--serve", "1", "--foxglove", "0.0.0.0:1"]))
    given = serve_options(p.parse_args(["--serve", "0.0.0.0:1", "--serve-token", "t"]))
    assert given == ServeOptions(("0.0.0.0", 1), "t")
    monkeypatch.setenv("VPENGINE_SERVE_TOKEN", "from-env")
    assert serve_options(p.parse_args(["--serve", "[::]:9"])) == ServeOptions(("::", 9), "from-env")


def test_where_another_door_owns_heads_the_view_refuses_head_commands_with_its_reason(engine):
    """Under ``vpengine ros2 --serve`` a head added through the view would have no topics: it says where to go."""
    why = "under vpengine ros2, add and remove heads on /vpengine/add_head and /vpengine/remove_head: they get topics"
    engine.add_head = engine.remove_head = lambda *a: pytest.fail(f"the engine was asked: {a}")
    with WebServer(engine, "127.0.0.1", 0, heads_elsewhere=why) as v:
        for method, path, body in (("POST", "api/heads", b'{"name": "det2", "model": "tiny_det"}'),
                                   ("DELETE", "api/heads/depth", None)):  # fmt: skip
            status, _, reply = request(v.url + path, method, body)
            assert status == 409 and json.loads(reply) == {"error": why}, (method, status, reply)
