"""The shipped checkpoint catalog is well-formed, and malformed catalogs are refused with a useful message."""

from __future__ import annotations

import json
import re
from urllib.parse import urlsplit

import pytest

from vpengine.models import catalog
from vpengine.models.catalog import SHIPPED, Catalog, CatalogError, Entry

# The recipe names the zoo uses (issue 3); every one of them must find its default checkpoint in the catalog.
SIZES = "sblg"
RECIPE_DEFAULTS = {
    **{f"dinov2_vit{s}14": f"dinov2_vit{s}14_pretrain" for s in SIZES},
    **{f"dinov2_vit{s}14_reg4": f"dinov2_vit{s}14_reg4_pretrain" for s in SIZES},
    **{f"dinov2_vit{s}14_dav2": f"depth_anything_v2_vit{s}" for s in "sbl"},
    **{f"dav2_depth_{s}": f"depth_anything_v2_vit{s}" for s in "sbl"},
    **{f"dinov2_linear_{ds}_{s}": f"dinov2_vit{s}14_{ds}_linear_head" for ds in ("ade20k", "voc2012") for s in SIZES},
}


@pytest.fixture(scope="module")
def raw() -> dict:
    return json.loads(SHIPPED.read_text())


def test_every_shipped_entry_has_the_required_fields_with_sane_values(raw):
    entries = raw["entries"]
    assert raw["schema"] == 1
    names = [e["name"] for e in entries]
    assert len(names) == len(set(names)), "duplicate names"
    for e in entries:
        where = e["name"]
        for key in ("url", "file", "size", "licence", "recipes", "sha256", "source"):
            assert key in e, f"{where}: no {key}"
        url = urlsplit(e["url"])
        assert url.scheme == "https" and url.netloc in ("dl.fbaipublicfiles.com", "huggingface.co"), where
        assert url.path.rsplit("/", 1)[-1] == e["file"], f"{where}: file name differs from the URL's"
        assert e["size"] is None or (isinstance(e["size"], int) and e["size"] > 1_000_000), where
        assert isinstance(e["licence"], str) and e["licence"], where
        assert isinstance(e["recipes"], list) and e["recipes"], where
        if e["sha256"] is None:
            assert len(e.get("sha256_missing", "")) > 20, f"{where}: a null sha256 needs a reason"
        else:
            assert re.fullmatch(r"[0-9a-f]{64}", e["sha256"]), where
            assert e["size"] is not None, f"{where}: a digest without a size"
            assert "sha256" in e["source"], f"{where}: the digest's source is not recorded"


def test_the_shipped_catalog_covers_the_zoo_and_each_recipe_default(raw):
    cat = catalog.shipped()
    expected = (
        {f"dinov2_vit{s}14{r}_pretrain" for s in SIZES for r in ("", "_reg4")}
        | {f"dinov2_vit{s}14_{ds}_linear_head" for s in SIZES for ds in ("ade20k", "voc2012")}
        | {f"depth_anything_v2_vit{s}" for s in "sbl"}
        | {f"facebook/dinov2-{n}" for n in ("small", "base", "large", "giant")}
    )
    assert set(cat.names()) == expected
    for recipe, name in RECIPE_DEFAULTS.items():
        assert cat.default_for(recipe) is not None, recipe
        assert cat.default_for(recipe).name == name, recipe
        assert recipe in cat.find(name).recipes
    # Depth-Anything-V2: Small is Apache-2.0, Base and Large are non-commercial.
    assert cat.find("depth_anything_v2_vits").licence == "Apache-2.0"
    assert cat.find("depth_anything_v2_vitl").licence == "CC-BY-NC-4.0"


def test_register_models_are_slightly_larger_than_their_plain_twins():
    # A cross-check of sizes taken from different sources: 4 register tokens add 4 x embed_dim floats (+ pickle).
    cat = catalog.shipped()
    dims = {"s": 384, "b": 768, "l": 1024, "g": 1536}
    for s, dim in dims.items():
        plain = cat.find(f"dinov2_vit{s}14_pretrain").size
        reg = cat.find(f"dinov2_vit{s}14_reg4_pretrain").size
        assert 4 * dim * 4 <= reg - plain <= 4 * dim * 4 + 10_000, s


def _entry(**kw) -> dict:
    base = {
        "name": "x",
        "url": "https://example.org/x.pth",
        "file": "x.pth",
        "sha256": "a" * 64,
        "size": 10,
        "licence": "MIT",
        "recipes": ["r"],
    }
    return {**base, **kw}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"sha256": "abc"}, "64 hexadecimal"),
        ({"sha256": None}, "sha256_missing must say why"),
        ({"url": "file:///etc/passwd"}, "http(s) URL"),
        ({"file": "../x.pth"}, "plain file name"),
        ({"file": "x.pth.part"}, "plain file name"),
        ({"file": ".cache"}, "plain file name"),
        ({"size": -1}, "positive number of bytes"),
        ({"licence": ""}, "licence"),
        ({"recipes": "r"}, "list of recipe names"),
        ({"name": "a/b/c"}, "at most one '/'"),
        ({"colour": "red"}, "unknown fields ['colour']"),
    ],
)
def test_malformed_entries_are_refused_naming_the_problem(change, message):
    with pytest.raises(CatalogError, match=re.escape(message)):
        Catalog.from_dict({"schema": 1, "entries": [_entry(**change)]})


def test_missing_fields_and_duplicates_are_refused():
    data = _entry()
    del data["licence"]
    with pytest.raises(CatalogError, match=r"missing fields \['licence'\]"):
        Catalog.from_dict({"entries": [data]})
    with pytest.raises(CatalogError, match="appears twice"):
        Catalog.from_dict({"entries": [_entry(), _entry()]})
    with pytest.raises(CatalogError, match="schema 2"):
        Catalog.from_dict({"schema": 2, "entries": []})


def test_use_swaps_the_active_catalog_and_restores_it():
    mine = Catalog([Entry.from_dict(_entry(name="only_mine"))])
    with catalog.use(mine):
        assert catalog.find("only_mine") is not None
        assert catalog.find("dinov2_vits14_pretrain") is None
    assert catalog.find("only_mine") is None
    assert catalog.find("dinov2_vits14_pretrain") is not None


def test_extra_catalog_files_from_the_environment_are_merged(tmp_path, monkeypatch):
    extra = tmp_path / "site.json"
    extra.write_text(json.dumps({"schema": 1, "entries": [_entry(name="site_model")]}))
    monkeypatch.setenv("VPENGINE_CATALOG", str(extra))
    assert catalog.find("site_model").url == "https://example.org/x.pth"
    assert catalog.find("dinov2_vits14_pretrain") is not None  # the shipped entries stay


def test_cache_paths_keep_the_upstream_file_name_and_flatten_slashes(tmp_path):
    e = catalog.shipped().find("facebook/dinov2-small")
    assert e.path(tmp_path) == tmp_path / "weights" / "facebook--dinov2-small" / "model.safetensors"


def test_hub_files_are_recognised_by_their_resolve_url_and_nothing_else():
    e = catalog.shipped().find("depth_anything_v2_vits")
    assert e.hub == catalog.HubFile("depth-anything/Depth-Anything-V2-Small", "main", "depth_anything_v2_vits.pth")
    assert catalog.shipped().find("dinov2_vits14_pretrain").hub is None  # dl.fbaipublicfiles.com
    hub = "https://huggingface.co/org/repo/resolve"
    assert Entry.from_dict(_entry(url=f"{hub}/refs%2Fpr%2F3/x.pth")).hub == catalog.HubFile(
        "org/repo", "refs/pr/3", "x.pth"
    )
    for url in (
        "http://huggingface.co/org/repo/resolve/main/x.pth",  # not https
        f"{hub}/main/sub/x.pth",  # in a subfolder: plain HTTP
        "https://huggingface.co/org/repo/blob/main/x.pth",  # the web page, not the file
        "https://example.org/org/repo/resolve/main/x.pth",
    ):
        assert Entry.from_dict(_entry(url=url)).hub is None, url
