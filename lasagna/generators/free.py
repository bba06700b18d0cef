"""``FreeLayer``: a per-pixel edit layer with no network, for per-image optimisation.

The layer is its own parameter: one unconstrained pre-activation u per pixel and channel, squashed
into the layer's range by the same parametrisation as ``LayerGenerator``'s head (``layer.activate``)
and initialised to the same identity edit, so a free layer and a generator are interchangeable in
the distillation loop (both are called ``model(base, labels)``; the free layer ignores the labels).
``FreeLayer.from_layer`` starts from given layer values instead (e.g. an amortised generator's
output, refined per image).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn

from lasagna.errors import LasagnaError
from lasagna.generators.layer import LayerSpec, activate, inverse
from lasagna.io.checkpoint import Pretrained

FORMAT = "lasagna.free_layer"


class FreeLayerConfig(BaseModel):
    """Everything that rebuilds a ``FreeLayer`` (saved as config.json beside the weights)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    layer: LayerSpec = Field(description="The edit layer it holds (blend, channels, range, squash).")
    batch: int = Field(1, ge=1, description="How many layers (one per image) it holds.")
    height: int = Field(ge=1)
    width: int = Field(ge=1)


class FreeLayer(Pretrained, nn.Module):
    """B per-pixel layers (B, C, H, W) as one parameter tensor (see the module docstring)."""

    FORMAT = FORMAT
    CONFIG = FreeLayerConfig

    def __init__(self, config: FreeLayerConfig):
        super().__init__()
        self.config = config
        u0 = config.layer.identity_preactivation().to(torch.float32)
        self.u = nn.Parameter(u0.view(1, -1, 1, 1).expand(config.batch, -1, config.height, config.width).clone())

    @property
    def spec(self) -> LayerSpec:
        return self.config.layer

    @classmethod
    def from_layer(cls, spec: LayerSpec, layer: Tensor) -> FreeLayer:
        """A free layer whose values start at ``layer`` (B, C, H, W) (``layer.inverse``; sigmoid channels
        are exact up to ``numerics.LOGIT_EPS`` at the range's ends)."""
        if layer.dim() != 4:
            raise LasagnaError(f"layer has shape {tuple(layer.shape)}; expected (B, C, H, W)", "layer")
        b, _, h, w = layer.shape
        model = cls(FreeLayerConfig(layer=spec, batch=b, height=h, width=w))
        with torch.no_grad():
            model.u.copy_(inverse(layer.detach().to(torch.float32), spec))
        return model

    def forward(self, base: Tensor | None = None, labels: Tensor | Sequence[str] | str | None = None) -> Tensor:
        """The layer (B, C, H, W). ``base``, if given, must have this layer's batch and size."""
        cfg = self.config
        if base is not None and (
            base.dim() != 4 or base.shape[0] != cfg.batch or tuple(base.shape[-2:]) != (cfg.height, cfg.width)
        ):
            raise LasagnaError(
                f"base has shape {tuple(base.shape)}; expected ({cfg.batch}, C, {cfg.height}, {cfg.width}) like this "
                "free layer",
                "base",
            )
        return activate(self.u, cfg.layer)
