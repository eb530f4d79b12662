"""A run's ``summary.json`` is valid JSON: what strict readers (jq, a browser, ``json.loads`` with no NaN) take."""

from __future__ import annotations

import json

import numpy as np

from vpengine.pipeline.summary import write_summary


def test_numbers_that_are_not_finite_are_null_and_numpy_numbers_plain(tmp_path):
    summary = {
        "models": {"depth": {"p50": float("nan"), "p99": np.float64("inf"), "runs": np.int64(3), "ok": np.bool_(True)}},
        "wall_s": np.float32(1.5),
        "rows": [(1, float("-inf"))],
    }
    write_summary(tmp_path, summary)
    text = (tmp_path / "summary.json").read_text()

    def strict(token: str) -> None:
        raise ValueError(f"not JSON: {token}")

    got = json.loads(text, parse_constant=strict)  # NaN, Infinity: refused, as strict readers do
    assert got == {"models": {"depth": {"p50": None, "p99": None, "runs": 3, "ok": True}}, "wall_s": 1.5,
                   "rows": [[1, None]]}  # fmt: skip
