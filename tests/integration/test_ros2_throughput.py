"""Throughput of the DDS bridge at 30 Hz (``vpengine bench ros2-bridge``), checked stage by stage.

At 640x480, with every frame taken in order (configs/tiny_every_frame.yaml), every frame comes in, every run comes
out and a frame the engine skips under load is counted. At 1080p two shared cores saturate (publisher, bridge, four
workers and subscriber serialising 8 MB depth images): the measured fractions are in benchmarks/results/ros2_bridge_throughput.json and
docs/ros2.md, and what is asserted there is what holds on any machine -- the publisher keeps its rate, every frame
the bridge received is accounted for, every output names a published frame, and the bridge's own CPU per frame fits
the 30 Hz budget.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests_paths import ROOT

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600), pytest.mark.xdist_group("dds")]


def _bench(
    tmp_path, size: str, config: str = "configs/tiny.yaml", output_qos: str = "latest", input_qos: str = "sensor"
) -> dict:
    p = subprocess.run(
        [sys.executable, "-m", "vpengine.cli.main", "bench", "ros2-bridge", "--out", str(tmp_path),
         "--sizes", size, "--seconds", "3", "--rate", "30", "--config", config, "--output-qos", output_qos,
         "--input-qos", input_qos],
        cwd=ROOT, capture_output=True, text=True, timeout=540,
    )  # fmt: skip
    assert p.returncode == 0, p.stdout + p.stderr
    res = json.loads((tmp_path / "ros2_bridge_throughput.json").read_text())
    assert res["machine"]["cores"] >= 1
    (run,) = res["runs"]
    return run


def test_bridge_at_640x480_30_hz_delivers_every_frame_it_runs_and_counts_the_rest(tmp_path):
    # every frame in order (input_mode: fifo): a moment's stall is caught up, not skipped to the newest; every output
    # kept for the subscriber (ROS 2's default keep last 10, where the bridge's default keeps only the newest);
    # frames in over reliable transport (ROS 2's default QoS), since best effort loses a frame whenever a fragment is
    # dropped. On an idle machine every frame comes out (ros2_bridge_throughput_every_result.json); a CI machine
    # whose two cores also run the publisher, the subscriber and the workers can stall past fifo's 4-frame lag, and
    # then the foundation model skips a frame (297-299 of 300 seen in 10 s), and with both cores kept busy by another program
    # the publisher's keep-last history can even replace a frame the stalled bridge had not taken (297 of 300):
    # how many arrive and run measures the machine. What must hold is that every frame the bridge took is run or
    # counted as skipped, and that every run reaches the subscriber.
    run = _bench(tmp_path, "640x480", "configs/tiny_every_frame.yaml", "default", input_qos="default")
    n = run["frames_published"]
    assert n == 90 and run["frame"] == "640x480 bgr8"  # 3 s at 30 Hz
    assert 0 < run["bridge_received"] <= n, run
    assert run["bridge_submitted"] + run["bridge_superseded"] == run["bridge_received"], run
    models = {k: {kk: float(vv) for kk, vv in v.items()} for k, v in run["models"].items()}
    fm = models["foundation"]
    assert fm["runs"] + fm["skipped"] == run["bridge_submitted"] and fm["runs"] > 0, fm
    for topic, t in run["topics"].items():
        head = topic.split("/")[2]
        assert t["published_by_bridge"] == models[head]["runs"], (topic, t, models[head])  # every run goes out
        # a subscriber that the busy cores stall falls more than its keep-last-10 history behind now and then (ROS 2's
        # default QoS drops the oldest then, by design): what it lost is within one history's depth
        assert t["published_by_bridge"] - 10 <= t["received"] <= t["published_by_bridge"], (topic, t)
        assert models[head]["runs"] + models[head]["skipped"] == fm["runs"], (topic, models[head])
        assert t["unknown_stamps"] == 0


def test_bridge_at_1080p_30_hz_accounts_for_every_frame(tmp_path):
    run = _bench(tmp_path, "1920x1080")
    n = run["frames_published"]
    assert n == 90 and run["publish_hz"] > 20 and run["frame"] == "1920x1080 bgr8"
    # transport in (sensor-data QoS, as cameras publish): best effort loses a frame when a fragment is dropped, i.e.
    # when the bridge's receive thread was starved of CPU while its 4 MB socket buffer (smaller than one 6 MB frame)
    # filled. How many arrive is a measurement of the machine (docs/ros2.md: 272-300 of 300 on an idle 2-core one);
    # what must hold on any machine, however loaded, is that frames arrive and every one that did is accounted for
    assert run["input_qos"] == "sensor" and run["bridge_received"] > 0, run
    models = {k: {kk: float(vv) for kk, vv in v.items()} for k, v in run["models"].items()}
    fm = models["foundation"]
    assert fm["runs"] + fm["skipped"] == run["bridge_submitted"]
    assert run["bridge_submitted"] + run["bridge_superseded"] == run["bridge_received"]
    for topic, t in run["topics"].items():
        head = topic.split("/")[2]
        assert t["unknown_stamps"] == 0, topic  # every output carries a published frame's stamp
        # the bridge published every run it collected but those a newer result of the head superseded; the rest
        # were counted as missed by its result stream (the bench waits until the bridge's diagnostics show it
        # drained before it stops)
        assert t["received"] > 0 and t["received"] <= t["published_by_bridge"], topic
        accounted = t["published_by_bridge"] + models[head]["results_missed"] + models[head]["outputs_superseded"]
        assert models[head]["runs"] == accounted, (topic, t, models[head], run["drain_s"])
    # the bridge's own CPU for one frame in and all its outputs out (decode, submit, results, convert, encode, write;
    # thread CPU time, so other load does not inflate it) fits the 33 ms budget of 30 Hz
    assert run["bridge_cpu_ms_per_frame_in_and_out"] < 33.3, (
        run["bridge_cpu_ms_per_input_frame"],
        run["bridge_cpu_ms_per_output_frame"],
    )
