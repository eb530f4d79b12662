"""The repository's own promises: README commands == CI, the README short and its examples working, every link
of the README and docs/ leading somewhere, lint and types clean."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests_paths import ROOT

README_MAX_WORDS = 1500
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    block = re.search(r"```bash\n(.*?)```", text, re.S)
    assert block, "README has no bash block"
    return [ln.strip() for ln in block.group(1).splitlines() if ln.strip()]


def test_ci_runs_exactly_the_readme_setup_and_test_commands():
    ci = [
        ln.strip()
        for ln in (ROOT / ".ci" / "run").read_text().splitlines()
        if ln.strip() and not ln.startswith("#") and not ln.startswith(("set ", "cd "))
    ]
    assert ci == readme_commands()[:2]
    assert len(readme_commands()) == 2


def test_readme_is_short():
    words = len((ROOT / "README.md").read_text().split())  # as `wc -w` counts them
    assert words <= README_MAX_WORDS, f"README.md has {words} words; at most {README_MAX_WORDS} (move detail to docs/)"


def _slug(heading: str) -> str:
    """GitHub's anchor for a Markdown heading: lower case, punctuation dropped, spaces as hyphens."""
    text = re.sub(r"[`*_]|\[([^\]]*)\]\([^)]*\)", lambda m: m.group(1) or "", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(md: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", md.read_text(), flags=re.S)  # a '#' comment in a code block is no heading
    return {_slug(h) for h in re.findall(r"^#+\s+(.*)$", text, re.M)}


def _links(md: Path) -> list[str]:
    """The targets of the Markdown links and images of ``md`` outside code blocks and spans."""
    text = re.sub(r"```.*?```", "", md.read_text(), flags=re.S)
    text = re.sub(r"`[^`\n]*`", "", text)
    return re.findall(r"!?\[[^\]]*\]\(([^)\s]+)\)", text)


@pytest.mark.parametrize("md", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_leads_to_a_file_and_heading_that_exist(md):
    bad = []
    for target in _links(md):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # https:, mailto: ...
            continue
        path, _, anchor = target.partition("#")
        dest = (md.parent / path).resolve() if path else md
        if not dest.exists():
            bad.append(f"{target}: no file {dest}")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            bad.append(f"{target}: no heading #{anchor} in {dest.name}")
    assert not bad, f"{md.name}: broken links: {bad}"


def test_link_check_sees_a_broken_link_and_a_broken_anchor(tmp_path):
    md = tmp_path / "a.md"
    md.write_text("# Top\n[ok](#top) [gone](missing.md) ![pic](x.png) [bad](#nowhere) `[not](a-link.md)`\n")
    assert _links(md) == ["#top", "missing.md", "x.png", "#nowhere"]
    assert _anchors(md) == {"top"}


def readme_python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)


def test_readme_has_python_examples():
    assert len(readme_python_blocks()) >= 3


@pytest.mark.timeout(400)
@pytest.mark.parametrize("index", range(len(readme_python_blocks())))
def test_readme_python_example_runs(index, tmp_path):
    """Each example on its own, as a reader would paste it: a fresh interpreter in an empty directory, with only what
    ships with vpengine (configs by name, samples)."""
    script = tmp_path / "example.py"
    script.write_text(readme_python_blocks()[index])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    p = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=360
    )
    assert p.returncode == 0, f"README example {index + 1} failed:\n{script.read_text()}\n{p.stdout}\n{p.stderr}"


_SECTIONS = {
    "input": "InputConfig",
    "runtime": "RuntimeConfig",
    "logging": "LoggingConfig",
    "weights": "WeightsConfig",
    "foundation_model": "FoundationModelConfig",
    "foundation_model.preprocess": "PreprocessConfig",
}


@pytest.mark.parametrize("md", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_docs_name_only_config_fields_that_exist(md):
    from vpengine import config

    text = md.read_text()
    blocks = re.findall(r"```.*?```", text, re.S)
    spans = " ".join([*blocks, *re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", text, flags=re.S))])
    pattern = r"(?<![\w/.-])(input|runtime|logging|weights|foundation_model(?:\.preprocess)?)\.(\w+)\b(?!\.)"
    bad = []
    for section, field in re.findall(pattern, spans):
        if field in ("md", "py", "yaml", "json"):  # a file name, not a field
            continue
        model = getattr(config, _SECTIONS[section])
        if field not in model.model_fields and f"{section}.{field}" not in _SECTIONS:
            bad.append(f"{section}.{field}")
    assert not bad, f"{md.name} names config fields that do not exist: {sorted(set(bad))}"


def _tool(name: str) -> str:
    exe = shutil.which(name, path=str(ROOT / ".venv" / "bin")) or shutil.which(name)
    if exe is None:
        pytest.fail(f"{name} is not installed (it is part of the dev extra)")
    return exe


@pytest.mark.timeout(300)
def test_ruff_lint_is_clean():
    p = subprocess.run([_tool("ruff"), "check", "src", "tests"], cwd=ROOT, capture_output=True, text=True)
    assert p.returncode == 0, p.stdout + p.stderr


def test_code_is_formatted():
    # one layout, so a diff shows what changed and not whose editor saved the file (fix: ruff format src tests)
    p = subprocess.run([_tool("ruff"), "format", "--check", "src", "tests"], cwd=ROOT, capture_output=True, text=True)
    assert p.returncode == 0, p.stdout + p.stderr


@pytest.mark.timeout(600)
def test_mypy_is_clean_on_transport_runtime_and_config():
    p = subprocess.run([sys.executable, "-m", "mypy"], cwd=ROOT, capture_output=True, text=True)
    assert p.returncode == 0, p.stdout + p.stderr
