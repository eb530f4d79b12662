"""GPU tests: run on the GPU machine with ``pytest -m gpu tests/gpu``.

Every test in this folder is marked ``gpu`` here as well (a forgotten marker must not make a CUDA test run, and
fail, in the CPU suite, whose default selection is ``-m 'not gpu'``). Tests that need CUDA use the ``require_cuda``
fixture, which skips them with the reason when no CUDA device is visible.
"""

from __future__ import annotations

from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    # tryfirst: the marker must be on the items before `-m` deselection looks at them.
    for item in items:
        if Path(str(item.fspath)).resolve().is_relative_to(HERE):
            item.add_marker(pytest.mark.gpu)


@pytest.fixture
def require_cuda() -> None:
    """Skip the test, saying why, unless a CUDA device is visible to PyTorch."""
    import torch

    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU (run on the GPU machine: pytest -m gpu tests/gpu)")
