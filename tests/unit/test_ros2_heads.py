"""Heads added and removed from ROS 2, through the core every transport shares (Note [Head commands]): the topics
an added head gets and a removed one loses, the model names, /diagnostics, each command's outcome, and the thread
that carries them out one at a time without holding the control thread.

No DDS here (tests/integration/test_ros2_bridge.py runs the same over DDS); the real engine in thread mode.
"""

from __future__ import annotations

import itertools
import json
import threading
import time

import pytest

from helpers.frames import frame
from helpers.waiting import Commands
from tests_paths import tiny
from vpengine.ros2 import cdr
from vpengine.ros2.control import ControlLoop
from vpengine.ros2.core import Ros2Core
from vpengine.ros2.heads import HeadCommands, HeadOutcome, named_in
from vpengine.ros2.messages import Header
from vpengine.ros2.outputs import image_out

pytestmark = pytest.mark.timeout(300)

DET2 = "{name: det2, model: tiny_det}"


def image(i: int):
    """A sensor_msgs/Image as the bridge hands it in (decoded from CDR)."""
    return cdr.decode_image(bytes(cdr.encode_image(image_out(frame(i), "bgr8", Header(1_700_000_000 + i, i)))))


class Topics:
    """A transport's hooks: the topics it was told to open and to close."""

    def __init__(self) -> None:
        self.opened: list = []
        self.closed: list = []

    def open(self, topics: list) -> None:
        self.opened += topics

    def close(self, topics: list) -> None:
        self.closed += topics


def outputs_by_head(core: Ros2Core, frames: range, seconds: float = 30.0) -> dict[str, set[str]]:
    """Feed ``frames`` and collect, per head, the topics its outputs went out on."""
    got: dict[str, set[str]] = {}
    for i in frames:
        assert core.handle_image(image(i)) is not None, core.rejected.counts
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            for t, _ in core.poll_outputs(0.1):
                got.setdefault(t.head, set()).add(t.topic)
            if set(core.head_infos) <= set(got):
                break
    return got


def status_names(core: Ros2Core) -> set[str]:
    return {s.name for s in core.diagnostics().status}


def interface_values(core: Ros2Core) -> dict[str, str]:
    return dict(next(s for s in core.diagnostics().status if s.name.endswith(": interface")).values)


def test_an_added_head_gets_its_topics_names_and_status_and_a_removed_one_loses_them():
    core = Ros2Core(tiny("thread"))
    core.start()
    hooks = Topics()
    try:
        assert outputs_by_head(core, range(1)).keys() == {"depth", "seg", "det"}
        out = core.add_head(DET2, hooks.open)
        assert out.ok and out.command == "add_head" and out.head == "det2", out
        assert out.topics == ("/vpengine/det2/detections",) == tuple(t.topic for t in hooks.opened)
        assert [(t.head, t.role, t.msgtype) for t in hooks.opened] == [
            ("det2", "detections", "vision_msgs/msg/Detection2DArray")
        ]
        assert "det2" in out.message and "/vpengine/det2/detections" in out.message
        assert core.model_names == list(out.model_names) == ["foundation", "depth", "seg", "det", "det2"]
        assert hooks.opened[0] in core.topics
        assert "vpengine: det2" in status_names(core)
        got = outputs_by_head(core, range(1, 3))
        assert got["det2"] == {"/vpengine/det2/detections"} and got["det"] == {"/vpengine/det/detections"}

        out = core.remove_head(" det2 ", hooks.close)
        assert out.ok and out.head == "det2" and out.topics == ("/vpengine/det2/detections",), out
        assert hooks.closed == hooks.opened
        assert core.model_names == list(out.model_names) == ["foundation", "depth", "seg", "det"]
        assert "/vpengine/det2/detections" not in {t.topic for t in core.topics}
        assert "vpengine: det2" not in status_names(core)
        assert "det2" not in outputs_by_head(core, range(3, 5))
        values = interface_values(core)
        assert (values["head_commands"], values["head_commands_rejected"]) == ("2", "0")
        assert values["last_head_command"] == "remove_head det2: ok: head 'det2' removed"
        # a removed head's topics may come back: a head of another kind under the name
        out = core.add_head('{"name": "det2", "model": "tiny_depth"}', hooks.open)  # JSON is YAML
        assert out.ok and out.topics == ("/vpengine/det2/depth",), out
        assert outputs_by_head(core, range(5, 6))["det2"] == {"/vpengine/det2/depth"}
    finally:
        core.stop()


def test_with_several_cameras_an_added_head_gets_a_topic_on_each_camera_it_serves():
    core = Ros2Core(tiny("thread"), cameras=["front", "rear"], overrides=["runtime.spare_heads=2"])
    core.start()
    hooks = Topics()
    try:
        rear = core.add_head("{name: seg2, model: tiny_seg, cameras: [rear]}", hooks.open)
        both = core.add_head("{name: depth2, model: tiny_depth}", hooks.open)
        assert rear.ok and both.ok, (rear, both)
        assert rear.topics == ("/vpengine/rear/seg2/classes",)
        assert both.topics == ("/vpengine/front/depth2/depth", "/vpengine/rear/depth2/depth")
        assert [(t.camera, t.head) for t in hooks.opened] == [("rear", "seg2"), ("front", "depth2"), ("rear", "depth2")]
        assert core.set_rate("seg2@rear", "2") == ("seg2@rear", 2.0)  # rate commands know the added head's lanes
        camera = {s.name: dict(s.values) for s in core.diagnostics().status}["vpengine: camera rear"]
        assert camera["seg2.target_hz"] == "2.00" and "depth2.target_hz" in camera, camera
        out = core.remove_head("depth2", hooks.close)
        assert out.topics == both.topics and hooks.closed == hooks.opened[1:]
    finally:
        core.stop()


def test_bad_head_commands_report_the_engines_error_and_change_nothing():
    core = Ros2Core(tiny("thread"))
    hooks = Topics()
    out = core.add_head(DET2, hooks.open)
    assert not out.ok and "has not started" in out.message and out.head == "det2"
    core.start()
    try:
        heads_before, topics_before = list(core.model_names), list(core.topics)
        stats_before = set(core.engine.stats()["models"])

        def refused(out: HeadOutcome, command: str, head: str | None, match: str) -> None:
            assert (out.ok, out.command, out.head, out.topics) == (False, command, head, ()), out
            assert match in out.message, out.message
            assert list(out.model_names) == core.model_names == heads_before
            assert core.topics == topics_before and not hooks.opened and not hooks.closed
            assert set(core.engine.stats()["models"]) == stats_before

        add, remove = core.add_head, core.remove_head
        refused(add("{name: seg, model: tiny_seg}", hooks.open), "add_head", "seg", "repeated: ['seg']")
        refused(
            add("{name: det2, model: tiny_det, no_such: 1}", hooks.open),
            "add_head",
            "det2",
            "heads.det2.no_such: unknown key",
        )
        refused(add("{name: det2, model: tiny_det, priority: 101}", hooks.open), "add_head", "det2", "priority")
        refused(add("just text", hooks.open), "add_head", None, "a mapping")
        refused(add("{name: [unclosed", hooks.open), "add_head", None, "")
        refused(remove("nope", hooks.close), "remove_head", "nope", "no head named 'nope'; heads: ['depth', 'seg'")
        refused(remove("foundation", hooks.close), "remove_head", "foundation", "foundation model serves every head")

        def no_publisher(topics: list) -> None:
            raise RuntimeError(f"cannot create a publisher for {topics[0].topic}")

        refused(add(DET2, no_publisher), "add_head", "det2", "cannot create a publisher for /vpengine/det2/detections")
        assert core.add_head(DET2, hooks.open).ok  # the seat given back takes it
        hooks.opened.clear()
        heads_before, topics_before, stats_before = list(core.model_names), list(core.topics), stats_before | {"det2"}
        refused(add("{name: det3, model: tiny_det}", hooks.open), "add_head", "det3", "no room for head 'det3'")
        for h in ("depth", "seg", "det"):
            assert core.remove_head(h, hooks.close).ok
        hooks.closed.clear()
        heads_before, topics_before = list(core.model_names), list(core.topics)
        stats_before = {"foundation", "det2"}
        refused(remove("det2", hooks.close), "remove_head", "det2", "'det2' is the engine's last head")
        values = interface_values(core)
        assert (values["head_commands"], values["head_commands_rejected"]) == ("4", "11")
        assert values["last_head_command"].startswith("remove_head det2: refused: 'det2' is the engine's last head")
    finally:
        core.stop()


def test_the_name_of_an_add_command_is_read_for_its_outcome_only_when_there_is_one():
    assert named_in(DET2) == "det2" and named_in('{"name": "x"}') == "x"
    assert named_in("just text") is None and named_in("{name: [1]}") is None and named_in(": :") is None


# ---------------------------------------------------------------------------------------------- head thread
class _SlowCore:
    """Adds take ``build_s`` (as a build and warm-up do); rates apply at once."""

    def __init__(self, build_s: float) -> None:
        self.build_s = build_s
        self.rates: list[float] = []
        self.running = 0
        self.most_at_once = 0
        self.order: list[str] = []

    def _work(self, what: str, seconds: float) -> None:
        self.running += 1
        self.most_at_once = max(self.most_at_once, self.running)
        time.sleep(seconds)
        self.order.append(what)
        self.running -= 1

    def add_head(self, text, open_topics):
        self._work(text, self.build_s)
        return HeadOutcome("add_head", text, True, f"head {text!r} added")

    def remove_head(self, name, close_topics):
        self._work(f"-{name}", 0.0)
        if name == "nope":
            return HeadOutcome("remove_head", name, False, "no head named 'nope'")
        return HeadOutcome("remove_head", name, True, "removed")

    def set_rate(self, key, value):
        self.rates.append(time.monotonic())
        return key, float(value)

    def set_priority(self, key, value):
        return key, int(value)

    def diagnostics(self):
        return time.monotonic()


def test_head_commands_run_one_at_a_time_off_the_control_thread_and_each_outcome_is_published(caplog):
    core = _SlowCore(build_s=1.0)
    commands = Commands()
    published: list[HeadOutcome] = []
    heads = HeadCommands(core, lambda t: None, lambda t: None, published.append)  # type: ignore[arg-type]
    diagnostics: list[float] = []
    loop = ControlLoop(core, diagnostics.append, commands.wait, period_s=0.2, heads=heads)  # type: ignore[arg-type]
    stop = threading.Event()
    threads = [threading.Thread(target=loop.run, args=(stop,)), threading.Thread(target=heads.run, args=(stop,))]
    for th in threads:
        th.start()
    try:
        with caplog.at_level("INFO", logger="vpengine.ros2"):
            for kind, text in (("add_head", "a"), ("add_head", "b"), ("remove_head", "a"), ("remove_head", "nope")):
                commands.put((kind, "", text))
            time.sleep(0.3)
            sent = time.monotonic()
            commands.put(("rate", "depth", "5"))  # while "a" builds
            deadline = time.monotonic() + 10
            while len(published) < 4 and time.monotonic() < deadline:
                time.sleep(0.02)
    finally:
        stop.set()
        for th in threads:
            th.join(10)
    (applied,) = core.rates
    assert applied - sent < 0.5  # not behind the build, 0.7 s more (a loaded machine stalls tens of ms)
    gaps = [b - a for a, b in itertools.pairwise(diagnostics)]
    assert max(gaps) < 0.7, gaps  # /diagnostics kept its beat through two builds of 1 s each
    assert core.order[:4] == ["a", "b", "-a", "-nope"] and core.most_at_once == 1
    assert [(o.command, o.head, o.ok) for o in published[:4]] == [
        ("add_head", "a", True),
        ("add_head", "b", True),
        ("remove_head", "a", True),
        ("remove_head", "nope", False),
    ]
    assert json.loads(published[3].text())["message"] == "no head named 'nope'"
    messages = [r.getMessage() for r in caplog.records]
    assert "add_head: head 'a' added" in messages
    assert "remove_head 'nope' refused: no head named 'nope'" in messages
    with pytest.raises(ValueError, match="head command 'rename_head' is not known; accepted: add_head, remove_head"):
        heads.put("rename_head", "x")


def test_an_outcome_is_json_a_ros_user_can_read():
    out = HeadOutcome("add_head", "det2", True, "head 'det2' added", ("/vp/det2/detections",), ("foundation", "det2"))
    assert json.loads(out.text()) == {
        "command": "add_head",
        "head": "det2",
        "ok": True,
        "message": "head 'det2' added",
        "topics": ["/vp/det2/detections"],
        "model_names": ["foundation", "det2"],
    }


def test_commands_still_queued_when_the_interface_stops_are_answered_not_left_waiting():
    core = _SlowCore(build_s=0.0)
    heads = HeadCommands(core, lambda t: None, lambda t: None, lambda o: None)  # type: ignore[arg-type]
    waiting = [heads.put("add_head", DET2), heads.put("remove_head", " seg ")]
    stop = threading.Event()
    stop.set()
    heads.run(stop)
    assert [w.result(timeout=1) for w in waiting] == [
        HeadOutcome("add_head", "det2", False, "the interface is stopping"),
        HeadOutcome("remove_head", "seg", False, "the interface is stopping"),
    ]
    assert core.order == []
