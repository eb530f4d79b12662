"""The paper harness's set-up: per-kind stream priorities (``--stream-priorities``) reach the models' configs, and a
bad item is refused by name; the seg head's upsampling choice (``--seg-upsample``) reaches the seg head alone."""

from __future__ import annotations

import pytest

from vpengine.bench.paper import Setup, parse_priorities


def test_priorities_parse_by_kind():
    assert parse_priorities("") == {}
    assert parse_priorities(" depth=-2, seg=0 ,foundation=-1,") == {"depth": -2, "seg": 0, "foundation": -1}


@pytest.mark.parametrize(
    ("text", "named"),
    [("sky=-1", "'sky=-1'"), ("depth", "'depth'"), ("depth=high", "'high' is not an integer")],
)
def test_a_bad_priority_item_is_named(text, named):
    with pytest.raises(ValueError, match=named):
        parse_priorities(text)


def test_priorities_reach_the_models_of_their_kind():
    setup = Setup(
        "cpu", "fp32", 120, 160, "tiny_vit", "tiny_depth", "tiny_seg", "tiny_det", {}, {}, "eager", 5, True,
        stream_priorities={"depth": -1, "foundation": -2},
    )  # fmt: skip
    cfg = setup.config([setup.head("depth", "d0"), setup.head("depth", "d1"), setup.head("seg", "seg")])
    assert [cfg.head(n).stream_priority for n in ("d0", "d1", "seg")] == [-1, -1, 0]
    assert cfg.foundation_model.stream_priority == -2


def test_seg_upsample_choice_reaches_the_linear_seg_head_only():
    setup = Setup(seg_upsample="torch")  # the full-size default models
    cfg = setup.config([setup.head("seg", "seg"), setup.head("depth", "depth")])
    assert cfg.head("seg").options == {"upsample": "torch"}
    assert cfg.head("depth").options == {}
    assert "seg upsample torch" in setup.engine_label
    auto = Setup()
    assert auto.config([auto.head("seg", "seg")]).head("seg").options == {}
    assert "upsample" not in auto.engine_label
