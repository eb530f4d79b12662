"""Note [Lanes]: every (model, camera) pair described once, at plan time; nobody else derives a camera's tag, reader
or control-block entry."""

from __future__ import annotations

import pickle
import re
from pathlib import Path

import pytest

from tests_paths import tiny
from vpengine.engine import Engine
from vpengine.runtime.lanes import make_lanes

SRC = Path(__file__).resolve().parents[2] / "src" / "vpengine"


def test_one_camera_is_one_lane_per_model_under_the_models_own_names():
    cfg = tiny("thread")
    lanes = make_lanes(cfg)
    assert list(lanes.by_model) == cfg.model_names()
    for model in cfg.model_names():
        (lane,) = lanes.of(model)
        assert (lane.model, lane.tag, lane.reader, lane.entry) == (model, 0, model, model)
        assert lane.only and lane.reader_tag is None  # its readers take every slot
    assert lanes.control_names() == [*cfg.model_names(), "+0"]  # and the one spare seat's (runtime.spare_heads)
    assert lanes.tag(None) == 0


def test_a_spare_seat_has_a_lane_on_every_camera_and_a_head_taking_it_renames_what_it_serves():
    cfg = tiny("thread", "cameras=[{name: front}, {name: rear}]", "runtime.spare_heads=2")
    lanes = make_lanes(cfg)
    assert lanes.seats == ("+0", "+1")
    assert [x.entry for x in lanes.seat_lanes("+1")] == ["+1@front", "+1@rear"]
    assert {"+0", "+0@front", "+0@rear", "+1", "+1@front", "+1@rear"} <= set(lanes.control_names())
    added = tiny("thread", "cameras=[{name: front}, {name: rear}]", "heads.2.cameras=[rear]")
    renames = make_lanes(added, ("+1",)).seat_renames("+0", "det")
    assert renames == {"+0": "det", "+0@rear": "det@rear"}  # its front lane stays the seat's, unused


def test_several_cameras_give_a_lane_per_served_camera_in_priority_order():
    cfg = tiny("thread", "cameras=[{name: front}, {name: rear}, {name: left}]", "heads.0.cameras=[left, front]")
    lanes = make_lanes(cfg)
    head = cfg.heads[0].name
    assert [(x.camera, x.tag, x.reader_tag) for x in lanes.of(head)] == [("front", 0, 0), ("left", 2, 2)]
    assert [x.entry for x in lanes.of("foundation")] == ["foundation@front", "foundation@rear", "foundation@left"]
    assert all(x.reader == x.entry and not x.only for x in lanes.of(head))
    names = lanes.control_names()
    assert names[: len(cfg.model_names())] == cfg.model_names()  # each model's own entry first
    assert f"{head}@left" in names and f"{head}@rear" not in names
    assert lanes.find(head, 1) is None and lanes.find(head, 2) is lanes.of(head)[1]
    assert lanes.select(head, "left") == (lanes.of(head)[1],) and lanes.select(head, None) == lanes.of(head)
    assert pickle.loads(pickle.dumps(lanes.of(head))) == lanes.of(head)  # crosses into a worker's child


def test_the_engine_hands_out_the_plans_lanes_with_their_configured_rates():
    cfg = tiny("thread", "cameras=[{name: front}, {name: rear}]", "heads.0.rate_hz=7")
    engine = Engine(cfg)  # planned, not started
    head = cfg.heads[0].name
    assert engine.lanes is engine.plan.lanes and engine.lanes == make_lanes(cfg)
    assert [lane.rate_hz for lane in engine.lanes.of(head)] == [7.0, 7.0]
    assert engine.cameras == ["front", "rear"]


def test_bad_cameras_and_models_are_refused_naming_the_good_ones():
    cfg = tiny("thread", "cameras=[{name: front}, {name: rear}]", "heads.0.cameras=[front]")
    lanes = make_lanes(cfg)
    head = cfg.heads[0].name
    with pytest.raises(ValueError, match=r"serves cameras \['front'\], not 'rear'"):
        lanes.select(head, "rear")
    with pytest.raises(ValueError, match=r"cameras \['front', 'rear'\]: say which one"):
        lanes.tag(None)
    with pytest.raises(ValueError, match=r"no camera named 'side'; cameras: \['front', 'rear'\]"):
        lanes.tag("side")
    with pytest.raises(KeyError, match="no model named 'nope'"):
        lanes.of("nope")


# What deriving a camera's tag, reader or entry looks like: indexing the camera list, or building ``model@camera``.
_DERIVING = [
    re.compile(r"camera_names\(\)\s*\.\s*index\("),
    re.compile(r"\bcam(era)?s\s*\.\s*index\("),
    re.compile(r"model_cameras\("),
    re.compile(r"""f["'][^"']*\{(model|name|spec\.name|m)\}@\{"""),
]


def test_camera_tags_readers_and_entries_are_derived_in_runtime_lanes_only():
    allowed = {SRC / "runtime" / "lanes.py", SRC / "config.py"}  # config defines model_cameras
    found = [
        f"{path.relative_to(SRC)}:{i}: {line.strip()}"
        for path in sorted(SRC.rglob("*.py"))
        if path not in allowed
        for i, line in enumerate(path.read_text().splitlines(), 1)
        if any(p.search(line) for p in _DERIVING)
    ]
    assert found == [], "derive these from the lanes (Note [Lanes] in runtime/lanes.py):\n" + "\n".join(found)
    assert _DERIVING[3].search('f"{model}@{camera}"')  # the patterns match what they are meant to
    assert _DERIVING[0].search("cfg.camera_names().index(c)")
