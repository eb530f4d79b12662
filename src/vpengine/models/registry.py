"""Recipe registry: config names -> model classes (imported lazily) plus preset options.

A config names a recipe (``dinov2_vits14``, ``tiny_depth``) or points at any importable class with
``package.module:Class`` -- that is how users add heads by config without touching vpengine.
"""

from __future__ import annotations

import importlib
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from vpengine.models.base import Model, ModelBuildError, Role


@dataclass(frozen=True)
class Recipe:
    name: str
    target: str  # "package.module:Class"
    role: Role
    defaults: dict[str, Any] = field(default_factory=dict)
    description: str = ""


_RECIPES: dict[str, Recipe] = {}


def register(name: str, target: str, role: Role, description: str = "", **defaults: Any) -> None:
    if name in _RECIPES and _RECIPES[name].target != target:
        raise ValueError(f"recipe {name!r} is already registered for {_RECIPES[name].target}")
    _RECIPES[name] = Recipe(name, target, role, dict(defaults), description)


def recipes(role: Role | None = None) -> list[Recipe]:
    _load_builtins()
    return [r for r in _RECIPES.values() if role is None or r.role == role]


def _import(target: str) -> type[Model]:
    module, _, attr = target.partition(":")
    if not module or not attr:
        raise ModelBuildError(f"model {target!r}: expected 'package.module:Class'")
    if module.startswith("."):
        raise ModelBuildError(f"model {target!r}: a relative module; name it from its package ('package.module:Class')")
    try:
        obj = getattr(importlib.import_module(module), attr)
    except ModuleNotFoundError as e:
        raise ModelBuildError(f"model {target!r} cannot be imported: {e}{_import_hint(module, e)}") from None
    except (ImportError, AttributeError) as e:
        raise ModelBuildError(f"model {target!r} cannot be imported: {e}") from None
    except Exception as e:  # the module's own code failed (a SyntaxError, an error at import): its traceback says where
        raise ModelBuildError(f"model {target!r}: importing {module!r} failed: {type(e).__name__}: {e}") from e
    if not (isinstance(obj, type) and issubclass(obj, Model)):
        raise ModelBuildError(f"model {target!r} is not a vpengine.models.Model subclass")
    return obj


def _import_hint(module: str, e: ModuleNotFoundError) -> str:
    """The fix for a user model's module that is not found: where Python looks, or the package its code lacks."""
    if not e.name or not (module == e.name or module.startswith(e.name + ".")):
        return f" (a module {module!r} imports: install it in this environment)"
    root = module.partition(".")[0]
    if e.name != root:  # the package is there: it lacks the module (a typo, or not the package meant)
        parent, _, child = e.name.rpartition(".")
        found = getattr(sys.modules.get(parent), "__path__", None)
        at = f" (found at {', '.join(found)})" if found else ""
        return f"; package {parent!r}{at} has no module {child!r}"
    here = Path.cwd()
    if (here / root).is_dir() or (here / f"{root}.py").is_file():
        where = (
            f"; {root!r} is in the current folder {str(here)!r}, where the vpengine command does not look: run with "
            "PYTHONPATH=. or install its package (pip install -e)"
        )
    else:
        where = "; put the folder that holds it on PYTHONPATH, or install its package (pip install -e)"
    return f"{where} (docs/models.md, Your own head)"


def resolve(name: str, role: Role) -> tuple[type[Model], dict[str, Any]]:
    """The model class and preset options for a config's ``model`` field."""
    _load_builtins()
    if ":" in name:
        cls = _import(name)
        if cls.role not in (None, role):
            raise ModelBuildError(f"model {name!r} is a {cls.role} model and cannot be used as a {role}")
        return cls, {}
    recipe = _RECIPES.get(name)
    if recipe is None:
        known = sorted(r.name for r in _RECIPES.values() if r.role == role)
        raise ModelBuildError(f"unknown {role} model {name!r}; known: {', '.join(known)} (or 'package.module:Class')")
    if recipe.role != role:
        raise ModelBuildError(f"model {name!r} is a {recipe.role} model and cannot be used as a {role}")
    return _import(recipe.target), dict(recipe.defaults)


_loaded = False


def _load_builtins() -> None:
    global _loaded
    if _loaded:
        return
    _loaded = True
    importlib.import_module("vpengine.models.recipes")
