"""Config loading: YAML/JSON, validation messages that name field, value and what is accepted, overrides."""

from __future__ import annotations

import json
import typing

import pytest
from pydantic import BaseModel

from tests_paths import ROOT, TINY
from vpengine.config import ConfigError, EngineConfig, dump_config, load_config

CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_every_shipped_config_is_valid(path):
    cfg = load_config(path)
    assert isinstance(cfg, EngineConfig)
    assert load_config(json.loads(json.dumps(cfg.model_dump(mode="json")))) == cfg  # round trip


def test_yaml_and_json_give_the_same_config(tmp_path):
    raw = {"mode": "thread", "heads": [{"name": "d", "model": "tiny_depth", "rate_hz": 5}]}
    (tmp_path / "a.json").write_text(json.dumps(raw))
    (tmp_path / "a.yaml").write_text("mode: thread\nheads:\n  - {name: d, model: tiny_depth, rate_hz: 5}\n")
    assert load_config(tmp_path / "a.json") == load_config(tmp_path / "a.yaml")


def test_unknown_key_names_the_path_and_the_accepted_keys():
    with pytest.raises(ConfigError) as e:
        load_config({"heads": [{"name": "d", "model": "tiny_depth", "rate": 5}]})
    msg = str(e.value)
    assert "heads.d.rate: unknown key" in msg and "rate_hz" in msg and "postprocess" in msg


def test_an_error_names_a_list_item_by_its_name_as_set_takes_it_and_quotes_the_value_once():
    with pytest.raises(ConfigError) as e:
        load_config(TINY, ["heads.depth.rate_hz=fast", "cameras=[{name: front}, {name: rear.left}]"])
    lines = str(e.value).splitlines()[1:]
    assert lines[0].startswith("  cameras.1.name: ")  # a name with a dot is no path: the index stands
    with pytest.raises(ConfigError) as e:  # nor is one that --set would read as an index
        load_config(TINY, ["cameras=[{name: '1'}, {name: rear}]"])
    assert str(e.value).splitlines()[1].startswith("  cameras.0.name: ")
    with pytest.raises(ConfigError) as e:  # pydantic's own "got ..." is no quote of the value: it is given
        load_config(TINY, ["input.height=14.5"])
    assert str(e.value).splitlines()[1].endswith("got a number with a fractional part (got 14.5)")
    assert lines[1] == (
        "  heads.depth.rate_hz: Value error, rate must be null (no limit) or a number of Hz from 0 to 10000 "
        '(0 pauses), got "fast"'
    )


def test_bad_values_name_field_value_and_what_is_accepted():
    with pytest.raises(ConfigError) as e:
        load_config(
            {
                "mode": "fiber",
                "device": "gpu0",
                "input": {"height": 5},
                "heads": [{"name": "d", "model": "tiny_depth", "rate_hz": -3}],
            }
        )
    msg = str(e.value)
    assert "mode: Input should be 'process' or 'thread' (got \"fiber\")" in msg
    assert "device" in msg and "'gpu0' is not one of: cpu, cuda, cuda:N" in msg
    assert "input.height: Input should be greater than or equal to 14 (got 5)" in msg
    assert "heads.d.rate_hz" in msg and "got -3" in msg


def test_duplicate_and_reserved_head_names_fail():
    with pytest.raises(ConfigError) as e:
        load_config({"heads": [{"name": "d", "model": "tiny_depth"}, {"name": "d", "model": "tiny_seg"}]})
    # where, as a field's error says it, and neither pydantic's "Value error," nor the whole config quoted
    assert str(e.value) == "invalid configuration:\n  heads: head names must be unique; repeated: ['d']"
    with pytest.raises(ConfigError, match=r"^invalid configuration:\n  heads.d.cameras: \['back'\] must be some of"):
        load_config({"heads": [{"name": "d", "model": "tiny_depth", "cameras": ["back"]}]})
    with pytest.raises(ConfigError, match="'foundation' is reserved"):
        load_config({"heads": [{"name": "foundation", "model": "tiny_depth"}]})
    with pytest.raises(ConfigError, match="must start with a letter"):
        load_config({"heads": [{"name": "1x", "model": "tiny_depth"}]})


def test_overrides_by_head_name_and_index_with_yaml_values():
    cfg = load_config(
        ROOT / "configs" / "tiny.yaml",
        [
            "heads.seg.rate_hz=5",
            "heads.0.rate_hz=null",
            "mode=thread",
            "input.width=320",
            "foundation_model.preprocess.size=224",
        ],
    )
    assert cfg.head("seg").rate_hz == 5 and cfg.head("depth").rate_hz is None
    assert cfg.mode == "thread" and cfg.input.width == 320
    assert cfg.foundation_model.preprocess.size == 224


def test_bad_overrides_are_clear():
    with pytest.raises(ConfigError, match="no entry named 'nope'; names: \\['depth', 'seg', 'det'\\]"):
        load_config(ROOT / "configs" / "tiny.yaml", ["heads.nope.rate_hz=5"])
    with pytest.raises(ConfigError, match="must look like key.path=value"):
        load_config(None, ["mode"])
    with pytest.raises(ConfigError, match="index 7 out of range"):
        load_config(ROOT / "configs" / "tiny.yaml", ["heads.7.rate_hz=1"])


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="is neither a file nor a shipped config"):
        load_config(tmp_path / "nope.yaml")
    (tmp_path / "bad.yaml").write_text("mode: [unclosed\n")
    with pytest.raises(ConfigError, match="is not valid YAML"):
        load_config(tmp_path / "bad.yaml")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="must hold a mapping"):
        load_config(tmp_path / "list.yaml")


def test_dump_is_loadable(tmp_path):
    cfg = load_config(ROOT / "configs" / "tiny.yaml")
    (tmp_path / "d.yaml").write_text(dump_config(cfg))
    assert load_config(tmp_path / "d.yaml") == cfg


def leaf_fields() -> dict[str, str | None]:
    """Every leaf field of EngineConfig as its dotted path -> description; a field that several models share by
    inheritance (ModelConfig's, in the foundation model and every head) counts once, as its first path."""
    found: dict[tuple[type, str], tuple[str, str | None]] = {}

    def models_in(annotation: object) -> list[type[BaseModel]]:
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            return [annotation]
        return [m for a in typing.get_args(annotation) for m in models_in(a)]

    def walk(model: type[BaseModel], prefix: str) -> None:
        for name, field in model.model_fields.items():
            inner = models_in(field.annotation)
            for sub in inner:
                walk(sub, f"{prefix}{name}.")
            if not inner:
                owner = next(c for c in reversed(model.__mro__) if name in getattr(c, "model_fields", {}))
                found.setdefault((owner, name), (prefix + name, field.description))

    walk(EngineConfig, "")
    return dict(found.values())


# The number of settings a user can meet. Each one is a question the user must understand; a new one replaces an
# old one or comes with a reason to raise this bound (issue 21).
# 42: heads[].accept_backbone_mismatch, the explicit ask to run a head on features it was not trained on (issue 30).
# 44: heads[].priority and cameras[].priority, who gives way when the device cannot serve every rate (issue 29).
# 45: runtime.spare_heads, how many heads may be added while running: room reserved at start (issue 29).
# 46: process (each model), which models share a worker process: fault isolation against a CUDA context's device
#     memory each, a trade only the user can make (issue 28).
MAX_LEAF_FIELDS = 46


def test_every_config_field_has_a_description_of_at_least_one_sentence():
    bare = [
        f"{path}: {text!r}"
        for path, text in leaf_fields().items()
        if not text or len(text.split()) < 3 or not text.rstrip().endswith(".")
    ]
    assert not bare, "fields without a one-sentence description:\n" + "\n".join(bare)


def test_the_config_has_at_most_max_leaf_fields():
    fields = leaf_fields()
    assert len(fields) <= MAX_LEAF_FIELDS, f"{len(fields)} leaf fields (at most {MAX_LEAF_FIELDS}):\n" + "\n".join(
        fields
    )


@pytest.mark.parametrize(
    "name, text, where, why",
    [
        ("flow.yaml", "mode: thread\nheads: [unclosed\n", "line 3, column 1", "expected ',' or ']'"),
        ("indent.yaml", "mode: thread\ndevice: cpu\n  extra: 1\n", "line 3, column 8", "mapping values are not"),
        ("tab.yaml", "mode: thread\n\tdevice: cpu\n", "line 2, column 1", "'\\t' that cannot start any token"),
        ("control.yaml", 'mode: thread\ndevice: "c\x01"\n', "line 2, column 11", "U+0001 is not allowed in YAML"),
        ("comma.json", '{"mode": "thread",\n "device": }\n', "line 2, column 12", "Expecting value"),
    ],
)
def test_a_syntax_error_is_one_line_naming_file_line_column_and_reason(tmp_path, name, text, where, why):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_config(path)
    msg = str(e.value)
    assert "\n" not in msg and "<unicode string>" not in msg, msg
    kind = "JSON" if name.endswith(".json") else "YAML"
    assert msg.startswith(f"config file {str(path)!r} is not valid {kind}: {where}: "), msg
    assert why in msg, msg


def test_mps_off_unquoted_is_off_in_a_file_and_on_the_command_line(tmp_path):
    # YAML 1.1 reads a bare `off` as false: the field must still mean "off", not fail with "got false"
    (tmp_path / "c.yaml").write_text("mps: off\n")
    assert load_config(str(tmp_path / "c.yaml")).mps == "off"
    assert load_config("tiny", ["mps=off"]).mps == "off"
    with pytest.raises(ConfigError, match="mps"):
        load_config("tiny", ["mps=true"])  # on is not a setting: auto or required say which


def test_process_mates_are_the_models_naming_one_process_in_process_mode_only():
    from tests_paths import tiny

    cfg = tiny("process", "heads.det.process=p", "foundation_model.process=p", "heads.seg.process=q")
    assert cfg.process_mates("det") == cfg.process_mates("foundation") == ["foundation", "det"]
    assert cfg.process_mates("seg") == ["seg"] and cfg.process_mates("depth") == ["depth"]
    assert tiny("thread", "heads.det.process=p", "foundation_model.process=p").process_mates("det") == ["det"]


def test_a_key_given_twice_is_refused_with_both_lines(tmp_path):
    """YAML keeps the last of a repeated key silently: a second heads block pasted below the first dropped every
    head above it. JSON's objects likewise."""
    f = tmp_path / "twice.yaml"
    f.write_text(
        "heads:\n  - {name: depth, model: tiny_depth}\n  - {name: seg, model: tiny_seg, rate_hz: 5, rate_hz: 50}\n"
    )
    with pytest.raises(ConfigError, match=r"key 'rate_hz' is given twice in one mapping \(lines 3 and 3\)"):
        load_config(f)
    f.write_text(
        "heads:\n  - {name: depth, model: tiny_depth}\n# added later\nheads:\n  - {name: det, model: tiny_det}\n"
    )
    with pytest.raises(ConfigError, match=rf"config file '{f}': key 'heads' is given twice .*\(lines 1 and 4\)"):
        load_config(f)
    j = tmp_path / "twice.json"
    j.write_text('{"device": "cpu", "device": "cuda"}')
    with pytest.raises(ConfigError, match=rf"config file '{j}': key 'device' is given twice in one JSON object"):
        load_config(j)
    f.write_text("a: &x {k: 1}\nfoundation_model: {model: tiny_vit}\nheads: [{name: d, model: tiny_depth}]\n")
    with pytest.raises(ConfigError, match="a: unknown key"):  # an anchor used once: no false alarm, the real error
        load_config(f)


def test_a_backend_option_typo_is_a_config_error_not_a_worker_traceback():
    """backend_options were checked in each worker after the processes started, with a traceback; the planning
    (in the parent, before any worker) now names the field, the backend and what it accepts."""
    from vpengine.runtime.plan import make_plan

    cfg = load_config(TINY, ["heads.depth.backend=compile", "heads.depth.backend_options.mod=x"])
    with pytest.raises(ConfigError) as e:
        make_plan(cfg)
    assert str(e.value) == (
        "heads.depth.backend_options: bad backend_options for backend 'compile': unknown key 'mod' "
        "(accepted: compiler, cudagraphs, fullgraph, mode, slot_bound, warmup_iters)"
    )
    assert make_plan(load_config(TINY, ["heads.depth.backend=compile", "heads.depth.backend_options.mode=default"]))


def test_a_rate_yaml_reads_as_a_date_is_refused_in_the_one_message():
    with pytest.raises(ConfigError, match=r"heads.depth.rate_hz: .*must be null \(no limit\).*got \"2024-01-01\""):
        load_config(TINY, ["heads.depth.rate_hz=2024-01-01"])


def test_an_unknown_key_close_to_a_known_one_is_guessed():
    with pytest.raises(ConfigError) as e:
        load_config(TINY, ["heads.depth.rate_hx=5", "runtime.nonsense=1"])
    lines = str(e.value).splitlines()
    assert lines[1].startswith("  heads.depth.rate_hx: unknown key (did you mean 'rate_hz'? accepted here: ")
    assert lines[2].startswith("  runtime.nonsense: unknown key (accepted here: ")  # nothing close: no guess


def test_a_key_given_twice_in_a_set_value_names_the_override():
    with pytest.raises(
        ConfigError,
        match=r"^override 'heads.depth.options=\{seed: 1, seed: 2\}': key 'seed' is given twice in one mapping; YAML",
    ):
        load_config(TINY, ["heads.depth.options={seed: 1, seed: 2}"])


def test_a_camera_named_in_an_override_or_a_head_of_a_config_without_cameras_says_there_are_none():
    """--set cameras.rear.priority=-1 (docs/config.md's example) on a config without cameras said "cameras: Input
    should be a valid list"; a head's unknown camera named the hidden default camera without a word."""
    with pytest.raises(ConfigError) as e:
        load_config(TINY, ["cameras.rear.priority=-1"])
    assert str(e.value) == (
        "override path cameras.rear: the config has no cameras (so none named 'rear'); add it first, e.g. "
        "--set 'cameras=[{name: rear}]'"
    )
    assert load_config(TINY, ["cameras=[{name: rear}]", "cameras.rear.priority=-1"]).cameras[0].priority == -1
    with pytest.raises(ConfigError, match=r"\(the config has no cameras: its one camera is 'camera'\)"):
        load_config(TINY, ["heads.depth.cameras=[rear]"])
