"""Triton kernels on CPU tensors: a kernel module rebuilt for Triton's interpreter for one test."""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from types import ModuleType

import pytest


def interpreted(monkeypatch: pytest.MonkeyPatch, name: str) -> Iterator[ModuleType]:
    """Yield module ``name`` with its kernels built for Triton's interpreter (CPU tensors); rebuilt as usual after."""
    pytest.importorskip("triton")
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    module = importlib.import_module(name)
    yield importlib.reload(module)
    monkeypatch.delenv("TRITON_INTERPRET")
    importlib.reload(module)
