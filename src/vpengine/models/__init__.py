"""The model interface and the model zoo."""

from vpengine.models.base import BuildContext, Model, ModelBuildError, Options, Pipeline
from vpengine.models.registry import recipes, register, resolve

__all__ = [
    "BuildContext",
    "Model",
    "ModelBuildError",
    "Options",
    "Pipeline",
    "recipes",
    "register",
    "resolve",
]
