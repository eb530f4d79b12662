"""models/ imports only what lies below it, without circles, and no private name of another module (issue 21)."""

from __future__ import annotations

import ast
from pathlib import Path

from tests_paths import ROOT

SRC = ROOT / "src"
MODELS = SRC / "vpengine" / "models"
# The command-line modules whose libraries live in models/ (training, weights, export).
CLI = [SRC / "vpengine" / "cli" / f"{name}.py" for name in ("train", "weights", "export")]
# What models/ may import from the project: itself and the layers below it.
BELOW = ("vpengine.models", "vpengine.config", "vpengine.specs")


def module_name(path: Path) -> str:
    return ".".join(path.relative_to(SRC).with_suffix("").parts)


def imports(path: Path) -> list[tuple[str, str | None]]:
    """(module, name) for every project import in ``path``, at any depth (lazy imports count too)."""
    found: list[tuple[str, str | None]] = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(a.name, None) for a in node.names if a.name.startswith("vpengine")]
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("vpengine"):
            found += [(node.module, a.name) for a in node.names]
    return found


def targets(module: str, name: str | None) -> str:
    """The module an import makes this one depend on (``from pkg import mod`` depends on ``pkg.mod``)."""
    sub = f"{module}.{name}"
    if name is not None and (SRC / Path(*sub.split("."))).with_suffix(".py").is_file():
        return sub
    return module


def test_models_import_nothing_above_them():
    upward = [
        f"{module_name(p)} imports {m}"
        for p in sorted(MODELS.glob("*.py"))
        for m, _ in imports(p)
        if m != "vpengine" and not m.startswith(BELOW)
    ]
    assert upward == []


def test_models_have_no_import_circles():
    graph = {
        module_name(p): {targets(m, n) for m, n in imports(p) if m.startswith("vpengine.models")}
        for p in MODELS.glob("*.py")
    }
    done: set[str] = set()

    def visit(node: str, path: list[str]) -> None:
        assert node not in path, "import circle: " + " -> ".join([*path[path.index(node) :], node])
        if node in done:
            return
        for nxt in sorted(graph.get(node, ())):
            visit(nxt, [*path, node])
        done.add(node)

    for node in sorted(graph):
        visit(node, [])


def test_no_private_name_of_another_module_is_imported():
    private = [
        f"{module_name(p)}: from {m} import {n}"
        for p in [*sorted(MODELS.glob("*.py")), *CLI]
        for m, n in imports(p)
        # a package's private module (models/_triton_upsample_argmax.py) is its own to import; names are not
        if n is not None and n.startswith("_") and not n.startswith("__") and targets(m, n) == m
    ]
    assert private == []
