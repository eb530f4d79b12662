"""The repository's own promises: README commands == CI, lint and types clean."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys

import pytest

from tests_paths import ROOT


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


def _tool(name: str) -> str:
    exe = shutil.which(name, path=str(ROOT / ".venv" / "bin")) or shutil.which(name)
    if exe is None:
        pytest.fail(f"{name} is not installed (it is part of the dev extra)")
    return exe


@pytest.mark.timeout(300)
def test_ruff_lint_is_clean():
    p = subprocess.run([_tool("ruff"), "check", "src", "tests"], cwd=ROOT, capture_output=True, text=True)
    assert p.returncode == 0, p.stdout + p.stderr


@pytest.mark.timeout(600)
def test_mypy_is_clean_on_transport_runtime_and_config():
    p = subprocess.run([sys.executable, "-m", "mypy"], cwd=ROOT, capture_output=True, text=True)
    assert p.returncode == 0, p.stdout + p.stderr
