"""What process mode on a GPU says when no MPS daemon answers (runtime/gpu.py no_mps_hint): a warning where the config
left the choice open and several workers could overlap; nothing where the user decided or nothing could overlap."""

from __future__ import annotations

import pytest

from tests_paths import tiny
from vpengine.config import load_config
from vpengine.runtime.gpu import no_mps_hint


def cfg(*sets: str):
    return load_config(tiny(), ["device=cuda", *sets])


def test_process_mode_left_to_auto_is_told_what_mps_buys_and_how_to_start_or_silence_it():
    hint = no_mps_hint(cfg("mode=process", "mps=auto"))
    assert hint is not None
    assert "the 4 workers' kernels take turns on the GPU" in hint
    assert "`vpengine mps start`" in hint and "mps: off" in hint


@pytest.mark.parametrize("sets", [("mode=thread", "mps=auto"), ("mode=process", "mps=off")])
def test_thread_mode_or_a_decision_is_not_warned(sets):
    assert no_mps_hint(cfg(*sets)) is None


def test_one_worker_has_nothing_to_overlap_with():
    one = cfg("mode=process", "mps=auto")
    one = load_config(one.model_dump() | {"heads": []})
    assert no_mps_hint(one) is None
