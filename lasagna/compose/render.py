"""Render a plan: ``render(plan or layers, ...) -> RenderResult(image (..., 3, H, W), skipped, evaluated)``.

Only the clipped rectangle of each live layer is touched. When nothing requires grad (or grad mode is
off) the banded in-place engine runs under ``torch.no_grad()``: no autograd graph, each input pixel
read once, the output written once — a 4-layer 2048² stack costs about as much as copying its bytes
(docs/BENCHMARKS.md, "Compositing"). When some live layer's colour, alpha, mask or opacity requires
grad, the layers below the first such layer are still composited that way (they are constants);
from there on ``grad_engine`` decides: ``"banded"`` runs the same fast forward and a banded backward with
closed-form derivatives that recomputes each band's backdrops instead of storing full-canvas
intermediates (``backward.py``); ``"autograd"`` records every blend as pure functions
(``engine.run_functional``; twice differentiable); ``"auto"`` (default) records where the recorded graph's
intermediates fit ``AUTO_RECORD_BYTES`` and runs banded above that. Both give the same gradients (tested); they reach
every live layer tensor, opacity and mask, and any module that produced them. From the first learned layer
up, a plan holding a group or an adjustment layer is always recorded (``differentiable_tail``).

Precision: ``dtype`` defaults to the promoted dtype of the live layers' colours (float32 for float32
layers); float64 is the reference. float16 and bfloat16 are computed in that dtype (inputs cast band
by band). Their documented error bound, ``half_precision_bound(dtype, live_layers)`` =
``HALF_PRECISION_ERROR[dtype] × (1 + live_layers)``, holds for ``clamp="layer"``, ``blend_space="srgb"``
multiply factors ≤ 1 and the blends that are 1-Lipschitz in the backdrop (all but overlay,
soft-light, color-dodge, color-burn and the non-separable four, whose divisions and slopes up to 2
amplify rounding): every blend is then 1-Lipschitz in the backdrop, so each live layer adds
at most a few roundings (≈ 8 unit roundoffs, inputs cast included) to the error. Factors above 1
amplify earlier errors by up to the factor, and the sRGB encode of ``blend_space="linear"`` by up to
12.92 in the dark toe. Measured maxima grow far slower (like √layers; docs/BENCHMARKS.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from lasagna.compose.backward import BandedGrad, grad_inputs
from lasagna.compose.engine import canvas_shape, first_grad_step, run_fast, run_functional, run_transparent
from lasagna.compose.plan import BlendSpace, ClampPolicy, RenderLayerSpec, RenderPlan, compile_plan
from lasagna.errors import LasagnaError

GradEngine = Literal["auto", "banded", "autograd"]

# "auto" records the tail (grad_engine="autograd") when its live steps times the canvas's bytes stay within
# this, else runs the banded backward. The recorded graph keeps about one canvas-sized intermediate per live
# step (measured: a training step of 4 learned layers at 2048² peaks 130 MB — 2.7 canvases of 48 MB — above
# the banded engine's), and it is the faster engine wherever it fits: training steps on this project's box
# (2 threads, lasagna.heap's thresholds; docs/BENCHMARKS.md, Compositing) took 23 vs 41 ms (4 layers, 2048²),
# 15 vs 52 ms (32 layers, 512²), 93 vs 134 ms (4 layers, 4096²), 0.42 vs 0.63 ms (4 layers, 256²). Above
# 1 GiB of intermediates (an 8192² stack: 768 MB a canvas) the banded engine's few band-sized buffers win.
AUTO_RECORD_BYTES = 1 << 30

# Per live layer, plus one for the background and the inputs' cast: 8 unit roundoffs of the dtype
# (bfloat16 u = 2^-8, float16 u = 2^-11); see the module docstring for when it holds.
HALF_PRECISION_ERROR = {torch.bfloat16: 8 * 2.0**-8, torch.float16: 8 * 2.0**-11}


def half_precision_bound(dtype: torch.dtype, live_layers: int) -> float:
    """Documented bound on max |render(dtype) − render(float64)| with ``live_layers`` live layers."""
    return min(1.0, HALF_PRECISION_ERROR[dtype] * (1 + live_layers))


@dataclass(frozen=True)
class RenderResult:
    """The composite ``image (..., 3, H, W)``, the skip reason of each culled layer, the live layer ids, and for a
    plan without a background (a transparent canvas) the composite's ``alpha (..., 1, H, W)``; ``image`` is then
    straight (not premultiplied) colour, 0 where alpha is 0."""

    image: Tensor
    skipped: dict[str, str]
    evaluated: list[str]
    alpha: Tensor | None = None


LayersOrPlan = RenderPlan | Sequence[RenderLayerSpec]


def as_plan(
    plan_or_layers: LayersOrPlan,
    canvas: tuple[int, int] | None = None,
    background: tuple[float, float, float] | None = (0.0, 0.0, 0.0),
    blend_space: BlendSpace = "srgb",
    clamp: ClampPolicy = "layer",
    cull: bool = True,
) -> RenderPlan:
    """A compiled plan: ``plan_or_layers`` itself, recompiled if its ``cull`` differs, or compiled from layers."""
    if isinstance(plan_or_layers, RenderPlan):
        p = plan_or_layers
        if p.cull == cull:
            return p
        return compile_plan(p.layers, p.canvas, p.background, p.blend_space, p.clamp, cull=cull)
    if canvas is None:
        raise LasagnaError(
            "canvas is missing; expected (height, width) when rendering a list of layers", where="render"
        )
    return compile_plan(plan_or_layers, canvas, background, blend_space, clamp, cull=cull)


def resolve_dtype(plan: RenderPlan, dtype: torch.dtype | None) -> torch.dtype:
    dtype = plan.dtype if dtype is None else dtype
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise LasagnaError(f"dtype is {dtype!r}; expected a floating-point torch.dtype", where="render")
    return dtype


def check_out(out: Tensor, shape: tuple[int, ...], dtype: torch.dtype, plan: RenderPlan) -> None:
    if not isinstance(out, Tensor) or tuple(out.shape) != shape or out.dtype != dtype or out.device != plan.device:
        got = f"{tuple(out.shape)} {out.dtype} on {out.device}" if isinstance(out, Tensor) else type(out).__name__
        raise LasagnaError(f"out is {got}; expected {shape} {dtype} on {plan.device}", where="render")


def render(
    plan_or_layers: LayersOrPlan,
    *,
    canvas: tuple[int, int] | None = None,
    background: tuple[float, float, float] | None = (0.0, 0.0, 0.0),
    blend_space: BlendSpace = "srgb",
    clamp: ClampPolicy = "layer",
    cull: bool = True,
    dtype: torch.dtype | None = None,
    out: Tensor | None = None,
    grad_engine: GradEngine = "auto",
) -> RenderResult:
    """Composite a ``RenderPlan`` (or bottom-to-top layers on ``canvas``) into ``(..., 3, H, W)``.

    ``cull=False`` blends zero-opacity, occluded and identity layers too (the result is the same;
    see ``plan.py``). ``background=None`` composites onto a transparent canvas: the result then has ``alpha``
    (``engine.run_transparent``). ``dtype`` overrides the compute dtype. ``out`` receives the image when no
    gradient is needed (it saves allocating ``H·W·3`` values per call in a loop). ``grad_engine``
    chooses how gradients are computed (module docstring).
    """
    check_grad_engine(grad_engine, "render")
    plan = as_plan(plan_or_layers, canvas, background, blend_space, clamp, cull)
    dtype = resolve_dtype(plan, dtype)
    shape = canvas_shape(plan)
    n = len(plan.steps)
    g = first_grad_step(plan)
    if plan.background is None:  # a transparent canvas: colour and alpha (engine.run_transparent)
        grad = g < n
        if out is not None:
            if grad:
                raise LasagnaError("out= was given but the render needs gradients; expected out=None", where="render")
            check_out(out, shape, dtype, plan)
        image, alpha = run_transparent(plan, dtype, grad, out)
        return RenderResult(image, dict(plan.skipped), plan.evaluated, alpha)
    if g == n:
        if out is not None:
            check_out(out, shape, dtype, plan)
        image = out if out is not None else torch.empty(shape, dtype=dtype, device=plan.device)
        run_fast(plan, 0, n, dtype, None, [image])
    else:
        if out is not None:
            raise LasagnaError("out= was given but the render needs gradients; expected out=None", where="render")
        prefix = None
        if g > 0:  # the layers below the first learned one are constants: composite them fast
            prefix = torch.empty(shape, dtype=dtype, device=plan.device)
            run_fast(plan, 0, g, dtype, None, [prefix], post=False)
        image = differentiable_tail(plan, g, dtype, prefix, grad_engine)
    return RenderResult(image, dict(plan.skipped), plan.evaluated)


def differentiable_tail(
    plan: RenderPlan, begin: int, dtype: torch.dtype, prefix: Tensor | None, grad_engine: GradEngine
) -> Tensor:
    """Composite ``plan.steps[begin:]`` over ``prefix`` (None: the background) with autograd.

    A tail holding a group is recorded (``run_functional``) whichever ``grad_engine`` is asked: the banded
    backward has closed forms for layers over an opaque canvas only, and a group is a function of its
    backdrop (pass-through) and of every child (``group.py``), an adjustment layer of its backdrop."""
    if resolve_grad_engine(plan, begin, dtype, grad_engine) == "autograd" or any(
        s.children is not None or s.spec.adjust is not None for s in plan.steps[begin:]
    ):
        return run_functional(plan, begin, dtype, prefix)
    return BandedGrad.apply(plan, begin, dtype, prefix, *grad_inputs(plan, begin))


def check_grad_engine(grad_engine: object, where: str) -> None:
    if grad_engine not in ("auto", "banded", "autograd"):
        raise LasagnaError(f"grad_engine is {grad_engine!r}; expected 'auto', 'banded' or 'autograd'", where=where)


def resolve_grad_engine(plan: RenderPlan, begin: int, dtype: torch.dtype, grad_engine: GradEngine) -> GradEngine:
    """The engine ``grad_engine`` stands for on ``plan.steps[begin:]``: itself, or for ``"auto"`` the recorded
    one while (live steps) × (canvas bytes) ≤ ``AUTO_RECORD_BYTES``, else the banded one."""
    if grad_engine != "auto":
        return grad_engine
    canvas = dtype.itemsize
    for d in canvas_shape(plan):
        canvas *= d
    return "autograd" if (len(plan.steps) - begin) * canvas <= AUTO_RECORD_BYTES else "banded"
