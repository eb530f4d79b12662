"""Import layering of the whole package, read with ``ast`` (nothing is imported): no circles between modules or
between folders, no private name of another module, models/ below the engine, and no citation of a missing file.

An import inside a function counts like one at the top of the module (it is a dependency all the same, only a later
one); an import under ``if TYPE_CHECKING:`` does not (it never runs). Importing ``a.b.c`` depends on ``a.b.c`` only,
not on the packages above it. A string that is a module's full dotted name (``"vpengine.bench.hop"``, or
``"vpengine.models.x:Class"``) is an import by name: ``importlib.import_module``, a table of commands or recipes,
a zygote's preload list. A package's own modules naming it (``resources.files("vpengine.web")``) do not count: it is
imported before them anyway.
"""

from __future__ import annotations

import ast
import functools
import itertools
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from tests_paths import ROOT

SRC = ROOT / "src"
PACKAGE = SRC / "vpengine"


def module_name(path: Path) -> str:
    parts = path.relative_to(SRC).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES: dict[str, Path] = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def is_package(module: str) -> bool:
    return MODULES[module].name == "__init__.py"


def is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


@dataclass
class Import:
    importer: str
    line: int
    module: str  # the module named after ``from`` (absolute), or the module of ``import``
    name: str | None  # the name after ``import`` in ``from module import name``; None for ``import module``
    bound: str | None = None  # the local name an ``import`` statement binds to that module (not for ``from``)
    by_name: bool = False  # a string naming the module (``importlib.import_module("vpengine.x")``, a registry entry)

    @property
    def target(self) -> str:
        """The project module this import makes the importer depend on (``from pkg import mod`` -> ``pkg.mod``)."""
        if self.name is not None and f"{self.module}.{self.name}" in MODULES:
            return f"{self.module}.{self.name}"
        return self.module

    def __str__(self) -> str:
        if self.by_name:
            return f"{self.importer} (line {self.line}): {self.module!r}, by name"
        what = f"import {self.module}" if self.name is None else f"from {self.module} import {self.name}"
        return f"{self.importer} (line {self.line}): {what}"


@dataclass
class Parsed:
    imports: list[Import] = field(default_factory=list)
    attributes: list[tuple[int, str, str]] = field(default_factory=list)  # (line, module, attribute)


def _type_checking_only(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _statements(tree: ast.AST) -> Iterator[ast.AST]:
    """Every node of ``tree`` except what lies under ``if TYPE_CHECKING:`` (its ``else`` still runs)."""
    stack = [tree]
    while stack:
        node = stack.pop()
        yield node
        if isinstance(node, ast.If) and _type_checking_only(node):
            stack.extend(node.orelse)
        else:
            stack.extend(ast.iter_child_nodes(node))


def _absolute(importer: str, node: ast.ImportFrom) -> str:
    if node.level == 0:
        return node.module or ""
    base = importer.split(".")
    if not is_package(importer):
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, node.module] if node.module else base)


def parse(module: str) -> Parsed:
    tree = ast.parse(MODULES[module].read_text(), filename=str(MODULES[module]))
    out = Parsed()
    bound: dict[str, str] = {}  # local name -> the project module it stands for
    for node in _statements(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "vpengine":
                    local = alias.asname or alias.name.split(".")[0]
                    bound[local] = alias.name if alias.asname else local
                    out.imports.append(Import(module, node.lineno, alias.name, None, local))
        elif isinstance(node, ast.ImportFrom):
            source = _absolute(module, node)
            if source.split(".")[0] != "vpengine":
                continue
            for alias in node.names:
                imp = Import(module, node.lineno, source, alias.name)
                out.imports.append(imp)
                if imp.target != source:  # ``from pkg import mod`` binds a module
                    bound[alias.asname or alias.name] = imp.target
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            named = node.value.split(":")[0]  # "vpengine.models.x:Class", as registries name an object
            if "." in named and named in MODULES and not module.startswith(named + "."):
                out.imports.append(Import(module, node.lineno, named, None, by_name=True))
    # ``mod._name`` for a name bound to a project module (best effort: no flow analysis, no shadowing).
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and is_private(node.attr):
            chain = _dotted(node.value)
            if chain is None or chain.split(".")[0] not in bound:
                continue
            head, *rest = chain.split(".")
            target = ".".join([bound[head], *rest])
            if target in MODULES:
                out.attributes.append((node.lineno, target, node.attr))
    return out


def _dotted(node: ast.expr) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        inner = _dotted(node.value)
        return None if inner is None else f"{inner}.{node.attr}"
    return None


@functools.cache
def parsed_modules() -> dict[str, Parsed]:
    """Every module of the package, parsed once per process on first use: not at collection, which every pytest
    worker pays whether or not it runs a test of this file."""
    return {m: parse(m) for m in MODULES}


# The import circles allowed, as the (importer, imported) edge by name that closes each. Keep it this short: each
# entry is an import that never runs while its importer is being imported.
ALLOWED_CIRCLES = {
    # The registry imports the recipes by name on the first lookup of a recipe, and each recipe module registers
    # itself with the registry's decorator as it is imported: a lazy registration, so reading a config imports no
    # model (nor torch).
    ("vpengine.models.registry", "vpengine.models.recipes"): "the model recipes register themselves on first lookup",
    # The zygote's PRELOAD names what its forked workers import, and imports it in the zygote process's main(), the
    # one that process.py's runner starts (with zygote.worker_path): a child process warming up, not an import of
    # process.py by zygote.py.
    ("vpengine.runtime.zygote", "vpengine.runtime.process"): "the zygote process preloads its workers' modules",
}


def module_graph(allowed: dict[tuple[str, str], str] | None = None) -> dict[str, dict[str, Import]]:
    """importer -> {imported module: the first import that makes the edge}, less the ``allowed`` edges."""
    allowed = ALLOWED_CIRCLES if allowed is None else allowed
    graph: dict[str, dict[str, Import]] = {m: {} for m in MODULES}
    for m, parsed in parsed_modules().items():
        for imp in parsed.imports:
            if imp.target in MODULES and imp.target != m and (m, imp.target) not in allowed:
                graph[m].setdefault(imp.target, imp)
    return graph


def folder(module: str) -> str:
    """The top-level node a module belongs to: its subpackage (``vpengine.io``) or itself (``vpengine.config``)."""
    return ".".join(module.split(".")[:2])


def folder_graph() -> dict[str, dict[str, Import]]:
    graph: dict[str, dict[str, Import]] = {folder(m): {} for m in MODULES}
    for m, edges in module_graph().items():
        for target, imp in edges.items():
            if folder(target) != folder(m):
                graph[folder(m)].setdefault(folder(target), imp)
    return graph


def cycles(graph: dict[str, dict[str, Import]]) -> list[str]:
    """One description per strongly connected component with more than one node, each naming a circle in it."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def connect(v: str) -> None:  # Tarjan; the graphs are small enough for recursion
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                components.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return [_describe(graph, c) for c in components]


def _describe(graph: dict[str, dict[str, Import]], component: list[str]) -> str:
    """A shortest circle through the component's first node, with the import that makes each edge."""
    members = set(component)
    start = component[0]
    previous: dict[str, str] = {}
    frontier = [start]
    while frontier and start not in previous:
        nxt = []
        for v in frontier:
            for w in sorted(graph[v]):
                if w in members and w not in previous:
                    previous[w] = v
                    nxt.append(w)
        frontier = nxt
    path = [start]
    while previous[path[-1]] != start:
        path.append(previous[path[-1]])
    path.append(start)
    path.reverse()
    steps = [f"  {a} -> {b}: {graph[a][b]}" for a, b in itertools.pairwise(path)]
    return f"circle among {', '.join(component)}:\n" + "\n".join(steps)


def test_the_graph_is_the_packages_and_a_circle_in_it_would_be_found():
    graph = module_graph()
    assert len(MODULES) > 80 and "vpengine.engine.core" in graph  # not an empty walk of a wrong folder
    assert "vpengine.runtime.supervisor" in graph["vpengine.engine.core"]
    looped = {**graph, "vpengine.config": {**graph.get("vpengine.config", {}), "vpengine.engine.core": "planted"}}
    assert cycles(looped)  # config <- ... <- engine, closed by the planted edge


def test_no_import_circle_between_modules():
    found = cycles(module_graph())
    assert not found, "\n".join(found)


def test_imports_by_name_are_edges_and_each_allowed_circle_is_needed():
    graph = module_graph({})
    assert "vpengine.bench.hop" in graph["vpengine.cli.bench"]  # cli/bench.py's table of benchmarks, by name
    assert graph["vpengine.cli.bench"]["vpengine.bench.hop"].by_name
    for edge, why in ALLOWED_CIRCLES.items():
        assert edge[1] in graph[edge[0]], f"{edge} is allowed but no longer imported: drop it ({why})"
        closed = module_graph({e: w for e, w in ALLOWED_CIRCLES.items() if e != edge})
        assert cycles(closed), f"{edge} closes no circle: drop it from ALLOWED_CIRCLES ({why})"


def imports_in(package: str) -> Iterator[Import]:
    """Every import (by name too) of the modules in ``package``."""
    for m, parsed in parsed_modules().items():
        if m == package or m.startswith(package + "."):
            yield from parsed.imports


def test_no_benchmark_imports_the_cli():
    """cli/ loads the benchmarks by name; bench/ runs the CLI only as a child process (``python -m vpengine``)."""
    found = [
        str(i)
        for i in imports_in("vpengine.bench")
        if i.target == "vpengine.cli" or i.target.startswith("vpengine.cli.")
    ]
    assert found == []


def test_no_import_circle_between_top_level_folders():
    found = cycles(folder_graph())
    assert not found, "\n".join(found)


def test_no_private_name_of_another_module_is_used():
    """``from x import _y`` and ``x._y`` reach into another module; a package's private submodule
    (models/_triton_upsample_argmax.py) is its own package's to import."""
    found = []
    for m, parsed in parsed_modules().items():
        for imp in parsed.imports:
            if imp.name is not None and is_private(imp.name):
                private_module = imp.target != imp.module
                if private_module and (m == imp.module or m.startswith(imp.module + ".")):
                    continue
                found.append(str(imp))
        for line, target, attr in parsed.attributes:
            if target != m:
                found.append(f"{m} (line {line}): {target}.{attr}")
    assert not found, "private names of other modules:\n" + "\n".join(found)


# What models/ may import from the project: itself and the layers below it.
BELOW_MODELS = (
    "vpengine.models",
    "vpengine.config",
    "vpengine.specs",
    "vpengine.colormaps",
    "vpengine._version",
    "vpengine.redact",  # imports nothing of vpengine
)


def test_models_import_nothing_above_them():
    upward = [
        str(i)
        for i in imports_in("vpengine.models")
        if i.target != "vpengine" and not i.target.startswith(BELOW_MODELS)
    ]
    assert upward == []


# A file of the repository named in src/ (code, docstrings, comments, bundled configs and pages): a path under one
# of these folders. Measurements live in docs/benchmarks.md and results files; a Note cites only what is there.
CITED = re.compile(r"(?<![\w/.])((?:benchmarks|docs|configs)/[\w./-]*\w)")


def test_every_repository_file_cited_in_src_exists():
    missing = [
        f"{path.relative_to(ROOT)}:{n}: {cited}"
        for path in sorted(PACKAGE.rglob("*"))
        if path.suffix in (".py", ".yaml", ".md", ".html", ".txt")
        for n, line in enumerate(path.read_text().splitlines(), 1)
        for cited in CITED.findall(line)
        if not (ROOT / cited).exists()
    ]
    assert not missing, "cited files that do not exist:\n" + "\n".join(missing)
