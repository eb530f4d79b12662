"""Configs that would hang, exhaust memory or quietly ruin outputs are refused with a ConfigError naming the file and
the value: alias bombs, deep nesting, binary files, NaN/infinite numbers, unbounded timeouts."""

from __future__ import annotations

import json
import time

import pytest
import torch

from tests_paths import tiny
from vpengine.config import MAX_DEPTH, ConfigError, load_config
from vpengine.engine import Engine, EngineStartError
from vpengine.specs import TensorSpec
from vpengine.transport import memory, ring

# 1 KB of YAML that stands for 9**9 (387 million) strings once its aliases are expanded
ALIAS_BOMB = "lol: &a0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
    f"l{i}: &a{i} [*a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}]\n"
    for i in range(1, 9)
)
# merge keys copy the merged entries as the file is read: 2**40 entries without a single list alias
MERGE_BOMB = "m0: &m0 {k0: 1, k1: 2}\n" + "".join(
    f"m{i}: &m{i} {{<<: [*m{i - 1}], x{i}: 1, y{i}: *m{i - 1}}}\n" for i in range(1, 40)
)


@pytest.mark.timeout(30)
@pytest.mark.parametrize("bomb", [ALIAS_BOMB, MERGE_BOMB], ids=["aliases", "merge-keys"])
def test_yaml_bombs_are_refused_fast_without_expanding_them(tmp_path, bomb):
    path = tmp_path / "bomb.yaml"
    path.write_text(bomb)
    assert len(bomb) < 2200
    t = time.monotonic()
    with pytest.raises(ConfigError, match="expands to more than 100000 values") as e:
        load_config(path)
    assert str(path) in str(e.value)
    assert time.monotonic() - t < 5


@pytest.mark.timeout(30)
def test_a_bomb_inside_postprocess_or_backend_options_is_refused_at_load(tmp_path):
    lines = ALIAS_BOMB.replace("\n", "\n    ").rstrip()
    path = tmp_path / "c.yaml"
    path.write_text(
        "mode: thread\nx_bombs:\n    " + lines + "\nheads:\n  - name: d\n    model: tiny_depth\n"
        "    postprocess: {junk: *a8}\n    backend_options: {junk: *a8}\n"
    )
    with pytest.raises(ConfigError, match="expands to more than"):
        load_config(path)
    bomb: list = ["lol"] * 9
    for _ in range(8):
        bomb = [bomb] * 9
    with pytest.raises(ConfigError, match="expands to more than"):  # the same through the API
        load_config({"heads": [{"name": "d", "model": "tiny_depth", "postprocess": {"x": bomb}}]})
    flow = "{" + ALIAS_BOMB.strip().replace("\n", ", ") + "}"  # the same bomb on one line
    with pytest.raises(ConfigError, match="expands to more than"):  # and through a command-line override
        load_config({"heads": [{"name": "d", "model": "tiny_depth"}]}, [f"heads.d.options={flow}"])
    self_ref = []
    self_ref.append(self_ref)
    with pytest.raises(ConfigError, match="contains itself"):
        load_config({"heads": [{"name": "d", "model": "tiny_depth", "options": {"x": self_ref}}]})


def test_deep_nesting_and_binary_files_name_the_file(tmp_path):
    deep = tmp_path / "deep.yaml"
    deep.write_text("a: " + "[" * 20000 + "]" * 20000 + "\n")
    with pytest.raises(ConfigError, match="nests too deeply") as e:
        load_config(deep)
    assert str(deep) in str(e.value)
    deep_json = tmp_path / "deep.json"
    deep_json.write_text('{"a": ' + "[" * 20000 + "]" * 20000 + "}")
    with pytest.raises(ConfigError, match="nests too deeply"):
        load_config(deep_json)
    nested = tmp_path / "nested.yaml"  # parses, but nests past the bound
    nested.write_text("heads:\n  - {name: d, model: tiny_depth, options: " + "[" * MAX_DEPTH + "]" * MAX_DEPTH + "}\n")
    with pytest.raises(ConfigError, match=f"nests deeper than {MAX_DEPTH} levels"):
        load_config(nested)
    for suffix in (".yaml", ".json"):
        binary = tmp_path / f"weights{suffix}"
        binary.write_bytes(bytes(range(256)) * 8)
        with pytest.raises(ConfigError, match="is not UTF-8 text") as e:
            load_config(binary)
        assert str(binary) in str(e.value)


def test_huge_values_are_clipped_in_error_messages():
    with pytest.raises(ConfigError) as e:
        load_config({"input": {"height": "9" * 1_000_000}, "heads": [{"name": "x" * 1_000_000, "model": "m"}]})
    msg = str(e.value)
    assert len(msg) < 5000
    assert "(1000002 characters)" in msg and "input.height" in msg


BAD = [
    ({"foundation_model": {"rate_hz": ".nan"}}, "from 0 to 10000"),
    ({"runtime": {"stop_timeout_s": ".inf"}}, "finite number"),
    ({"runtime": {"ready_timeout_s": ".inf"}}, "finite number"),
    ({"runtime": {"batch_window_ms": ".inf"}}, "finite number"),
    ({"runtime": {"hang_timeout_s": ".nan"}}, "finite number"),
    ({"runtime": {"stop_timeout_s": 1e9}}, "less than or equal to 600"),
    ({"runtime": {"hang_timeout_s": 0}}, "greater than 0"),
]


@pytest.mark.parametrize(("raw", "why"), BAD, ids=[json.dumps(b[0])[:40] for b in BAD])
def test_values_that_ruin_outputs_or_make_stop_unbounded_are_refused(tmp_path, raw, why):
    path = tmp_path / "c.yaml"
    path.write_text(json.dumps(raw).replace('".nan"', ".nan").replace('".inf"', ".inf"))
    with pytest.raises(ConfigError, match=why):
        load_config(path)


def test_mailboxes_that_do_not_fit_free_memory_are_refused_up_front_naming_their_size(monkeypatch):
    assert memory.free_bytes(torch.device("cpu")) > 0  # this machine's MemAvailable (or its cgroup's limit)
    monkeypatch.setattr("vpengine.runtime.plan.free_bytes", lambda device: 100_000)
    cfg = tiny("thread", "input.height=1080", "input.width=1920", "foundation_model.input_mode=fifo")
    allocated = []
    monkeypatch.setattr(ring, "allocate", lambda *a, **k: allocated.append(a) or memory.allocate(*a, **k))
    with pytest.raises(EngineStartError) as e:
        Engine(cfg).start()
    msg = str(e.value)
    assert (
        "the mailboxes need" in msg
        and "of host memory (out.depth 49.8 MB, input 43.5 MB" in msg
        and "only 0.1 MB is free" in msg
    )
    assert not allocated  # refused before anything was allocated


def test_an_allocation_the_system_refuses_names_the_ring_and_its_size(monkeypatch):
    def enomem(*a, **k):
        raise OSError(12, "Cannot allocate memory")

    monkeypatch.setattr(ring, "allocate", enomem)
    with pytest.raises(MemoryError, match=r"ring 'big': cannot allocate 0.52 GB \(8 slots of 64800000 bytes\)"):
        ring.SlotRing.create("big", {"x": TensorSpec((16200000,), "float32")}, 8, [ring.ReaderDecl("r")])
