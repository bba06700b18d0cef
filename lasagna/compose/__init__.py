"""The compositor: pure tensor functions that turn a layer stack into an image, differentiably.

- ``blend``     one function per blend mode (W3C, opaque backdrop) in ``BLEND_FUNC``, in-place twins
                in ``BLEND_INPLACE``, and the clamp policy (``clamp_needed``);
- ``color``     sRGB ↔ linear light (IEC 61966-2-1);
- ``layer``     ``LayerTensors``: a layer's colour, alpha and mask with cached statistics;
- ``plan``      ``RenderLayerSpec`` / ``RenderGroupSpec`` → ``compile_plan`` → ``RenderPlan`` (rectangles,
                skip reasons),
                and ``plan_from_document`` for a ``lasagna.document`` stack;
- ``render``    ``render(plan or layers) -> RenderResult(image, skipped, evaluated)``;
- ``group``     groups: compositing onto a backdrop with alpha, isolated and pass-through groups;
- ``renderer``  ``Renderer``: repeated renders with a prefix cache;
- ``fused``     opt-in compiled kernels of the W3C modes for the banded forward (``set_fused``).

Of the document tier only the blend names are imported (``lasagna.document.blend`` declares them; the kernel
tables here implement one function per name); ``plan_from_document`` reads a document by attribute.
"""

from lasagna.compose.blend import (
    BLEND_FUNC,
    BLEND_INPLACE,
    BLEND_MODES,
    clamp_needed,
    get_blend,
    multiply,
    multiply_,
    normal,
    normal_,
    plus,
    plus_,
    screen,
    screen_,
)
from lasagna.compose.color import linear_to_srgb, srgb_to_linear
from lasagna.compose.fused import fused_enabled, set_fused
from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import (
    PlanStep,
    RenderGroupSpec,
    RenderLayerSpec,
    RenderPlan,
    compile_plan,
    plan_from_document,
)
from lasagna.compose.render import HALF_PRECISION_ERROR, RenderResult, half_precision_bound, render
from lasagna.compose.renderer import DEFAULT_CACHE_BYTES, Renderer

__all__ = [
    "BLEND_FUNC",
    "BLEND_INPLACE",
    "BLEND_MODES",
    "clamp_needed",
    "get_blend",
    "normal",
    "multiply",
    "screen",
    "plus",
    "normal_",
    "multiply_",
    "screen_",
    "plus_",
    "srgb_to_linear",
    "linear_to_srgb",
    "LayerTensors",
    "RenderLayerSpec",
    "RenderGroupSpec",
    "PlanStep",
    "RenderPlan",
    "compile_plan",
    "plan_from_document",
    "RenderResult",
    "render",
    "HALF_PRECISION_ERROR",
    "half_precision_bound",
    "Renderer",
    "DEFAULT_CACHE_BYTES",
    "set_fused",
    "fused_enabled",
]
