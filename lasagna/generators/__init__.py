"""Edit-layer generators: the conditioned U-Net and the free per-pixel layer, one output parametrisation.

- ``layer``  ``LayerSpec`` (blend, channels, range, squash), the squash ``activate`` / ``inverse``
             with the identity-edit start, and ``composite(base, layer, spec)`` via the compositor;
- ``unet``   ``LayerGenerator`` (config ``LayerGeneratorConfig``): base + condition → layer;
- ``free``   ``FreeLayer`` (config ``FreeLayerConfig``): the layer as its own parameter.

Both are called ``model(base, labels) -> layer`` and saved as ``model.safetensors`` + ``config.json``.
"""

from lasagna.generators.free import FreeLayer, FreeLayerConfig
from lasagna.generators.layer import LayerSpec, activate, clamp_inward, composite, inverse, split
from lasagna.generators.unet import LayerGenerator, LayerGeneratorConfig

__all__ = [
    "FreeLayer",
    "FreeLayerConfig",
    "LayerGenerator",
    "LayerGeneratorConfig",
    "LayerSpec",
    "activate",
    "clamp_inward",
    "composite",
    "inverse",
    "split",
]
