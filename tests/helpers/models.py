"""Small user-style heads for build-time checks."""

from __future__ import annotations

from vpengine.models.base import BuildContext, Model
from vpengine.models.tiny import TinyDepthHead, TinyHeadOptions
from vpengine.specs import TensorSpec


class NeedsMissingFeature(Model):
    role = "head"

    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        m = cls()
        m.input_spec = {"patch.9": TensorSpec((1, 16, 32), "float32")}
        m.output_spec = {"y": TensorSpec((1,), "float32")}
        return m


class TrainedElsewhere(TinyDepthHead):
    @classmethod
    def from_config(cls, ctx: BuildContext) -> Model:
        m = cls(ctx, TinyHeadOptions())
        m.meta["trained_on"] = "dinov2_vitl14"
        return m
