"""Note [Give way]: the governor's decisions on made-up snapshots (no threads, no sleeps: time is a number), and the
control-block side of priorities (caps, skip reasons, deadline misses) on a real control block."""

from __future__ import annotations

import math
import threading
import time

import pytest

from tests_paths import tiny
from vpengine.config import ConfigError
from vpengine.runtime.control import ControlBlock
from vpengine.runtime.governor import FLOOR_HZ, HOLD_S, SETTLE_S, Governor, LaneView, Policy
from vpengine.runtime.lanes import make_lanes
from vpengine.runtime.priority import mps_below_normal, stream_levels


def view(entry, key, achieved, claim=30.0, p99=0.01, deadline=math.nan, span=1.0):
    return LaneView(entry, key, claim, achieved, p99, deadline, span)


def run(policy, make, t0, seconds, dt=0.1):
    """Decide every ``dt`` for ``seconds`` from ``t0`` on the snapshots ``make(caps)`` gives; the caps each time."""
    caps, history = {}, []
    t = t0
    while t < t0 + seconds:
        caps = policy.decide(make(caps), t)
        history.append((t, dict(caps)))
        t += dt
    return t, history


def lanes_under_load(caps, hi_holds=False):
    """hi (priority 10) misses its 30 Hz unless told it holds; mid (5) and lo (0) run at what their cap lets them."""

    def at(entry):
        return 30.0 if caps.get(entry) is None else caps[entry]

    return [
        view("hi", (10, 0), 30.0 if hi_holds else 15.0),
        view("mid", (5, 0), at("mid")),
        view("lo", (0, 0), at("lo")),
    ]


def test_overload_caps_the_lowest_priority_first_and_never_the_highest():
    p = Policy()
    t, history = run(p, lanes_under_load, 0.0, 1.0)
    first = next(caps for _, caps in history if any(c is not None for c in caps.values()))
    assert first["lo"] is not None and first["mid"] is None and first["hi"] is None
    assert first["lo"] < 30.0
    # it goes on missing: lo reaches the floor, then mid gives way too; hi never
    _, history = run(p, lanes_under_load, t, 10.0)
    assert all(caps["hi"] is None for _, caps in history)
    last = history[-1][1]
    assert last["lo"] == FLOOR_HZ and last["mid"] == FLOOR_HZ
    mid_capped = next(t for t, caps in history if caps["mid"] is not None)
    lo_floor = next(t for t, caps in history if caps["lo"] == FLOOR_HZ)
    assert lo_floor <= mid_capped


def test_a_lane_far_short_of_its_claim_gets_lower_lanes_to_the_floor_within_about_a_second():
    p = Policy()
    _, history = run(p, lanes_under_load, 0.0, 3.0)  # hi at half its claim
    assert next(t for t, caps in history if caps["lo"] == FLOOR_HZ) <= 1.5


def test_under_a_load_that_stays_failed_probes_are_undone_and_grow_rare_and_a_load_that_falls_is_given_back():
    """The device affords lo at most 3 Hz beside hi: each probe above that makes hi miss and is undone, and the
    wait before the next one doubles (without that a probe would fail every second). Then the load falls (hi holds
    whatever lo does): lo's cap comes off within seconds."""
    p = Policy()

    def plant(caps):
        lo = caps.get("lo")
        fits = lo is not None and lo <= 3.0
        return [view("hi", (1, 0), 30.0 if fits else 15.0), view("lo", (0, 0), 30.0 if lo is None else lo)]

    t, history = run(p, plant, 0.0, 30.0)
    over = [(caps["lo"] is None or caps["lo"] > 3.0) for _, caps in history]
    settled = over.index(False)
    probes_too_far = sum(1 for a, b in zip(over[settled:], over[settled + 1 :]) if b and not a)
    assert 1 <= probes_too_far <= 10, probes_too_far
    assert sum(over[settled:]) < 0.2 * len(over[settled:])
    caps_lo = [caps["lo"] for _, caps in history][settled:]
    for i in range(1, len(caps_lo) - 1):
        if over[settled + i] and not over[settled + i - 1]:  # a probe too far: undone, back where it was
            after = next((c for c in caps_lo[i + 1 :] if c != caps_lo[i]), None)
            assert after in (None, caps_lo[i - 1]), (caps_lo[i - 1], caps_lo[i], after)
    _, history = run(p, lambda caps: [view("hi", (1, 0), 30.0), view("lo", (0, 0), caps.get("lo") or 30.0)], t, 10.0)
    freed = next(u for u, caps in history if caps["lo"] is None)
    assert freed - t <= 8.0 and history[-1][1]["lo"] is None


def test_caps_come_off_when_the_high_lane_holds_again_highest_first():
    p = Policy()
    t, _ = run(p, lanes_under_load, 0.0, 10.0)
    _, history = run(p, lambda caps: lanes_under_load(caps, hi_holds=True), t, 30.0)
    assert history[-1][1] == {"hi": None, "mid": None, "lo": None}
    freed = {e: next(t for t, caps in history if caps[e] is None) for e in ("mid", "lo")}
    assert freed["mid"] <= freed["lo"]
    assert not p.throttling


def test_equal_priorities_never_throttle_each_other():
    p = Policy()
    _, history = run(p, lambda caps: [view(e, (3, 1), 10.0) for e in ("a", "b", "c")], 0.0, 10.0)
    assert all(c is None for _, caps in history for c in caps.values())


def test_only_lanes_below_the_one_that_misses_give_way():
    """mid misses while hi holds: lo is capped, hi and mid are not; and a lane that misses with nothing below it left
    to give changes nothing."""
    p = Policy()

    def lanes(caps):
        return [view("hi", (10, 0), 30.0), view("mid", (5, 0), 12.0), view("lo", (0, 0), 30.0)]

    _, history = run(p, lanes, 0.0, 10.0)
    last = history[-1][1]
    assert last["lo"] == FLOOR_HZ and last["mid"] is None and last["hi"] is None


def test_a_deadline_miss_counts_like_a_rate_miss():
    p = Policy()

    def lanes(caps):
        return [view("hi", (1, 0), 30.0, p99=0.050, deadline=1 / 30), view("lo", (0, 0), 30.0)]

    _, history = run(p, lanes, 0.0, 2.0)
    assert history[-1][1]["lo"] is not None


def test_no_decision_before_there_is_evidence():
    """Right after a change (or at the first look) a lane that misses is not judged until SETTLE_S has passed, and a
    lane whose claim is too low for the evidence (a few runs) is not judged at all."""
    p = Policy()
    caps = p.decide(lanes_under_load({}), 0.0)
    caps = p.decide(lanes_under_load(caps), SETTLE_S / 2)
    assert all(c is None for c in caps.values())
    slow = [view("hi", (10, 0), 0.0, claim=1.0, span=1.0), view("lo", (0, 0), 30.0)]
    for i in range(50):
        caps = Policy().decide(slow, i * 0.1)
    assert caps["lo"] is None


def test_a_priority_change_moves_the_caps_with_the_ranks_at_once():
    p = Policy()
    t, _ = run(p, lanes_under_load, 0.0, 1.5)
    assert p.decide(lanes_under_load({}), t)["lo"] is not None
    swapped = [view("hi", (0, 0), 15.0), view("mid", (5, 0), 30.0), view("lo", (10, 0), 30.0)]
    caps = p.decide(swapped, t + 0.1)  # one decision later: the one now lowest carries the cap
    assert caps["lo"] is None and caps["hi"] is not None and caps["mid"] is None


def test_head_priority_ranks_before_camera_priority():
    """depth@rear (head 5, camera 0) outranks seg@front (head 0, camera 5): seg@front gives way before it."""
    p = Policy()

    def lanes(caps):
        return [
            view("depth@front", (5, 5), 10.0),
            view("depth@rear", (5, 0), 30.0 if caps.get("depth@rear") is None else caps["depth@rear"]),
            view("seg@front", (0, 5), 30.0 if caps.get("seg@front") is None else caps["seg@front"]),
        ]

    _, history = run(p, lanes, 0.0, 1.0)
    first = next(caps for _, caps in history if any(c is not None for c in caps.values()))
    assert first["seg@front"] is not None and first["depth@rear"] is None and first["depth@front"] is None


def test_no_flapping_while_the_high_lane_holds_without_margin():
    """Its latency near (not past) the deadline: caps neither cut nor raised."""
    p = Policy()
    t, _ = run(p, lanes_under_load, 0.0, 1.0)
    before = p.decide(lanes_under_load({}), t)

    def lanes(caps):
        return [view("hi", (10, 0), 30.0, p99=0.9 / 30, deadline=1 / 30), *lanes_under_load(caps)[1:]]

    _, history = run(p, lanes, t + 0.1, 5 * HOLD_S)
    assert history[-1][1] == before


# ------------------------------------------------------------------------------------ the control block side
@pytest.fixture()
def ctl():
    c = ControlBlock.create(["foundation", "hi", "lo"])
    yield c
    c.close()


def test_the_rate_obeyed_is_the_lower_of_target_and_cap(ctl):
    assert ctl.rate("lo") is None
    ctl.set_cap("lo", 4.0)
    assert ctl.rate("lo") == 4.0 and ctl.target("lo") is None
    ctl.set_rate("lo", 2.0)
    assert ctl.rate("lo") == 2.0 and ctl.held_reason("lo") == "rate"
    ctl.set_rate("lo", 10.0)
    assert ctl.rate("lo") == 4.0 and ctl.held_reason("lo") == "priority"
    ctl.set_rate("lo", 0)
    assert ctl.rate("lo") == 0  # a pause stays a pause
    ctl.set_cap("lo", None)
    ctl.set_rate("lo", 10.0)
    assert ctl.rate("lo") == 10.0 and ctl.held_reason("lo") == "rate"


def test_skips_by_reason_sum_to_skipped(ctl):
    ctl.skip("lo", "rate", 2)
    ctl.skip("lo", "priority", 3)
    ctl.skip("lo", "overload")
    snap = ctl.snapshot("lo")
    assert snap["skipped"] == 6
    assert snap["skipped_by"] == {"rate": 2, "priority": 3, "overload": 1}


def test_deadline_misses_are_outputs_later_than_one_target_period(ctl):
    ctl.record_run("hi", 0.0, 0.01, 0.2, 1)  # no target: no deadline
    ctl.set_rate("hi", 10.0)
    ctl.record_run("hi", 1.0, 0.01, 0.05, 2)
    ctl.record_run("hi", 2.0, 0.01, 0.15, 3)
    assert ctl.get("hi", "deadline_misses") == 1
    ctl.record_run("hi", 3.0, 0.01, 0.02, 4)  # queued in time ...
    ctl.amend_last_run("hi", 0.2, 0.2)  # ... done too late (Note [Result hand-off])
    ctl.amend_last_run("hi", 0.25, 0.25)  # amended again: one miss, not two
    assert ctl.snapshot("hi")["deadline_misses"] == 2


def test_governor_caps_lanes_in_the_control_block_and_the_foundation_only_as_far_as_its_top_consumer():
    """Two cameras; depth (priority 10, 30 Hz) serves front only and gets 15 Hz; seg (0) serves both. Seg's lanes
    are capped; the foundation's rear lane (seg only) is capped with seg's, its front lane (depth) never."""
    cfg = tiny(
        "thread",
        "cameras=[{name: front}, {name: rear}]",
        "heads=[{name: depth, model: tiny_depth, cameras: [front], priority: 10, rate_hz: 30}, "
        "{name: seg, model: tiny_seg}]",
    )
    lanes = make_lanes(cfg)
    cams = lanes.cameras
    control = ControlBlock.create(lanes.control_names())
    try:
        for m, of_model in lanes.by_model.items():
            for lane in of_model:
                control.set_rate(lane.entry, lane.rate_hz)
            control.set_state(m, 3)  # running
        gov = Governor(control, cfg, lanes, clock=lambda: 0.0)
        assert control.get("foundation@front", "priority") == 10 and control.get("foundation@rear", "priority") == 0
        t, n = 0.0, 0
        for _ in range(40):  # 4 s: each camera at 30 Hz, depth at 15 Hz
            t += 0.1
            for c in cams:
                control.add(f"foundation@{c}", "runs", 3)
            for k in range(3):
                n += 1
                if n % 2:
                    control.record_run("depth@front", t + k / 30, 0.01, 0.01, n)
            gov.step(t)
        assert control.cap("depth@front") is None and control.cap("foundation@front") is None
        for entry in ("seg@front", "seg@rear"):
            assert control.cap(entry) is not None and control.rate(entry) == control.cap(entry)
        assert control.cap("foundation@rear") == control.cap("seg@rear")
        # the priority changes at run time: seg above depth, and the caps move with it at once
        gov.set_priority("seg", 20)
        gov.step(t + 0.1)
        assert control.cap("seg@front") is None and control.cap("seg@rear") is None
        assert control.cap("depth@front") is not None
        with pytest.raises(ValueError, match="101"):
            gov.set_priority("seg", 101)
        with pytest.raises(KeyError, match="heads: \\['depth', 'seg'\\]"):
            gov.set_priority("nope", 1)
        with pytest.raises(ValueError, match="serves cameras \\['front'\\], not 'rear'"):
            gov.set_priority("depth", 1, camera="rear")
        gov.set_priority(None, 7, camera="rear")
        assert control.get("seg@rear", "camera_priority") == 7 and control.get("seg@front", "camera_priority") == 0
        assert control.get("seg@front", "priority") == 20  # the failed calls changed nothing
    finally:
        control.close()


# ------------------------------------------------------------------------------------- config and the device
def test_priorities_in_the_config_are_bounded_and_overridable():
    cfg = tiny("thread", "cameras=[{name: front}, {name: rear}]", "heads.depth.priority=5", "cameras.rear.priority=-3")
    assert cfg.head("depth").priority == 5 and cfg.cameras[1].priority == -3 and cfg.head("seg").priority == 0
    with pytest.raises(ConfigError, match="heads.depth.priority"):
        tiny("thread", "heads.depth.priority=101")


def written_levels(cfg) -> dict[str, int]:
    """The stream level the governor writes for each model at start (the same in all of a model's lanes)."""
    lanes = make_lanes(cfg)
    control = ControlBlock.create(lanes.control_names())
    try:
        Governor(control, cfg, lanes)
        return {m: int(control.get(of[0].entry, "stream_level")) for m, of in lanes.by_model.items()}
    finally:
        control.close()


def test_stream_and_mps_priority_follow_the_config_and_stay_default_when_equal():
    equal = tiny("process")
    assert set(written_levels(equal).values()) == {0}
    assert not any(mps_below_normal(equal, m) for m in equal.model_names())
    cfg = tiny("process", "heads.depth.priority=10", "heads.seg.priority=5", "heads.det.mps_priority=normal")
    assert written_levels(cfg) == {"foundation": 2, "depth": 2, "seg": 1, "det": 0}
    assert [mps_below_normal(cfg, m) for m in cfg.model_names()] == [False, False, True, False]  # det: its own say


def test_more_distinct_priorities_than_stream_levels_keep_the_most_important_apart():
    few = stream_levels({"a": -5, "b": 0, "c": 7})
    assert few == {"a": 0, "b": 1, "c": 2}  # counted from the default up
    many = stream_levels({f"m{p}": p for p in range(6)}, top=3)
    assert many == {"m5": 3, "m4": 2, "m3": 1, "m2": 0, "m1": 0, "m0": 0}  # the least important share the default


def test_the_governor_writes_each_models_stream_level_and_a_priority_change_moves_it():
    """Note [Stream priority at run time] in runtime/device.py: the level a worker's stream should have, from the
    current priorities, in every lane of its model."""
    cfg = tiny("thread", "cameras=[{name: front}, {name: rear}]", "heads.det.priority=3")
    lanes = make_lanes(cfg)
    control = ControlBlock.create(lanes.control_names())
    try:
        gov = Governor(control, cfg, lanes)

        def levels() -> dict[str, set[int]]:
            return {
                m: {int(control.get(lane.entry, "stream_level")) for lane in of} for m, of in lanes.by_model.items()
            }

        assert levels() == {"foundation": {1}, "depth": {0}, "seg": {0}, "det": {1}}  # as the config says
        assert written_levels(cfg) == {m: min(v) for m, v in levels().items()}
        gov.set_priority("seg", 9, camera="rear")  # one lane raised: its model's stream goes up for every camera
        assert levels() == {"foundation": {2}, "depth": {0}, "seg": {2}, "det": {1}}
        gov.set_priority("det", 0)
        gov.set_priority("seg", 0, camera="rear")
        assert levels() == {"foundation": {0}, "depth": {0}, "seg": {0}, "det": {0}}  # equal: all at the default
        gov.set_priority(None, 7, camera="rear")  # a camera's priority ranks lanes, not streams
        assert levels() == {"foundation": {0}, "depth": {0}, "seg": {0}, "det": {0}}
    finally:
        control.close()


def test_a_priority_change_while_a_head_is_seated_counts_it_in_the_levels_and_unseat_drops_it():
    cfg = tiny("thread")
    added = tiny("thread", "heads=[{name: depth, model: tiny_depth}, {name: seg, model: tiny_seg}, "
                 "{name: det, model: tiny_det}, {name: det2, model: tiny_det, priority: 5}]")  # fmt: skip
    lanes, more = make_lanes(cfg), make_lanes(added, ())
    control = ControlBlock.create(more.control_names())
    try:
        gov = Governor(control, cfg, lanes)

        def level(m: str) -> int:
            return int(control.get(more.of(m)[0].entry, "stream_level"))

        gov.seat(added, more)
        assert (level("det2"), level("foundation"), level("depth")) == (1, 1, 0)
        gov.set_priority("depth", 0)  # any change rewrites the levels: the seated head still counts
        assert (level("det2"), level("foundation")) == (1, 1)
        gov.unseat()  # the add failed
        assert level("foundation") == 0
        gov.relane(added, more)  # or it succeeded
        gov.set_priority("seg", 0)
        assert (level("det2"), level("foundation"), level("seg")) == (1, 1, 0)
    finally:
        control.close()


def test_the_governor_thread_sleeps_while_priorities_are_equal_and_set_priority_wakes_it():
    cfg = tiny("thread")
    lanes = make_lanes(cfg)
    control = ControlBlock.create(lanes.control_names())
    gov = Governor(control, cfg, lanes, tick_s=0.01)
    steps = []
    woke = threading.Event()

    def step(now=None):
        steps.append(now)
        woke.set()
        return {}

    gov.step = step
    gov.start()
    try:
        time.sleep(0.3)  # 30 ticks' worth: the equal priorities of the default need no decision
        assert steps == []
        gov.set_priority("depth", 5)
        assert woke.wait(10.0), "set_priority did not wake the governor"
        n, deadline = len(steps), time.monotonic() + 10
        while len(steps) <= n + 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(steps) > n + 3  # priorities differ now: it ticks
        gov.set_priority("depth", 0)
        time.sleep(0.1)
        n = len(steps)
        time.sleep(0.3)
        assert len(steps) <= n + 1  # equal again: asleep (one tick under way may end); ticking gives ~30
    finally:
        gov.stop()
        control.close()
