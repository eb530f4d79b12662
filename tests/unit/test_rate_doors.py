"""One rate check for every door that takes a rate (``vpengine.checks.rate``): the config, ``Engine.set_rate``, the
ROS 2 core's rate commands and the live view's ``PUT /api/rate``. Each refuses the same bad values with the same
message, naming the value and the accepted range, spelled as its door writes values (the config and the live
view: null, "5"; a ROS 2 service's number: a negative number or inf; its set_rate topic's text names its own words)."""

from __future__ import annotations

import math

import pytest

from tests_paths import tiny
from vpengine.checks import MAX_RATE_HZ
from vpengine.config import ConfigError
from vpengine.engine import Engine
from vpengine.web.server import parse_rate

ONE_MESSAGE = r"must be None \(no limit\) or a number of Hz from 0 to 10000 \(0 pauses\), got "
BAD = [(math.nan, "nan"), (-1.0, "-1.0"), (MAX_RATE_HZ + 1, "10001.0"), ("5", "'5'")]


@pytest.fixture(scope="module")
def engine():
    with Engine(tiny("thread")) as e:
        yield e


@pytest.mark.parametrize(
    ("yaml", "shown"), [(".nan", "NaN"), ("-1", "-1"), ("10001", "10001"), ("'5'", '"5"'), ("None", '"None"')]
)
def test_the_config_refuses_a_bad_rate(yaml, shown):
    """The one message, spelled as a config is written: null for no limit (YAML's None is a string)."""
    with pytest.raises(ConfigError, match=ONE_MESSAGE.replace("None", "null") + shown) as e:
        tiny("thread", f"heads.seg.rate_hz={yaml}")
    assert ".rate_hz:" in str(e.value)


def test_the_config_takes_the_ends_of_the_range():
    assert tiny("thread", "heads.seg.rate_hz=0").head("seg").rate_hz == 0.0
    assert tiny("thread", f"heads.seg.rate_hz={MAX_RATE_HZ}").head("seg").rate_hz == MAX_RATE_HZ


@pytest.mark.parametrize(("bad", "shown"), BAD)
def test_set_rate_refuses_a_bad_rate_and_keeps_the_old_one(engine, bad, shown):
    engine.set_rate("seg", 4.0)
    with pytest.raises(ValueError, match="rate for 'seg' " + ONE_MESSAGE + shown):
        engine.set_rate("seg", bad)
    assert engine.rate("seg") == 4.0
    engine.set_rate("seg", MAX_RATE_HZ)
    assert engine.rate("seg") == MAX_RATE_HZ


@pytest.mark.parametrize(
    ("body", "shown"),
    [(b'{"hz": NaN}', "NaN"), (b'{"hz": -1}', "-1"), (b'{"hz": 10001}', "10001"), (b'{"hz": "5"}', '"5"')],
)
def test_the_live_view_refuses_a_bad_rate(body, shown):
    """The one message, its values spelled as the JSON body spells them."""
    with pytest.raises(ValueError, match="rate for 'seg' " + ONE_MESSAGE.replace("None", "null") + shown):
        parse_rate(body, "seg")


def test_a_ros2_rate_above_the_cap_gets_the_one_message_and_is_counted():
    from vpengine.ros2.core import Ros2Core

    core = Ros2Core(tiny("thread"))
    core.start()
    try:
        # text, as the set_rate topic carries it: the topic's own message, with the range and its words for no limit
        with pytest.raises(ValueError, match=r"rate '10001' is not a rate; accepted: a number of Hz from 0 to 10000"):
            core.set_rate("seg", "10001")
        # a number, as services and parameters carry it: the one message, "no limit" spelled as a number says it
        with pytest.raises(
            ValueError, match="rate for 'depth' " + ONE_MESSAGE.replace("None", "a negative number or inf") + "20000.0"
        ):
            core.set_rate("depth", 20000.0)
        assert core.counters["rate_commands_rejected"] == 2 and core.counters["rate_commands"] == 0
        assert core.engine.rate("seg") is None and core.engine.rate("depth") is None  # tiny: unlimited, unchanged
    finally:
        core.stop()
