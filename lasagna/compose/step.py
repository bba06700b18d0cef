"""What one live plan step reads when it is blended: its colour (an adjustment's, of the backdrop), its alpha, and
the clamp after it.

Shared by the forward engines (``engine.py``), the group compositor (``group.py``) and the banded
backward (``backward.py``), so all of them read a layer the same way.
"""

from __future__ import annotations

import torch
from torch import Tensor

from lasagna.compose.blend import Alpha, dissolve_alpha
from lasagna.compose.color import linear_to_srgb, srgb_to_linear
from lasagna.compose.plan import PlanStep


def _color(step: PlanStep, sl: tuple, dtype: torch.dtype, grad: bool) -> Tensor:
    """The layer's colour under ``sl``, decoded to linear light if the step says so, in ``dtype``."""
    t = step.spec.tensors
    if step.decode:
        cs = srgb_to_linear(t.color[sl]) if grad and t.color.requires_grad else t.decoded_color()[sl]
    else:
        cs = t.color[sl]
    return cs if cs.dtype == dtype else cs.to(dtype)


def _adjusted(step: PlanStep, Cb: Tensor, dtype: torch.dtype) -> Tensor:
    """An adjustment layer's colour over the backdrop colour ``Cb`` (unpremultiplied): its function of ``Cb``, of
    the sRGB-encoded ``Cb`` in the linear blend space (Photoshop adjusts encoded values)."""
    f = step.spec.adjust
    Cb = Cb if Cb.dtype == dtype else Cb.to(dtype)
    if step.decode:
        return srgb_to_linear(f(linear_to_srgb(Cb.clamp(0.0, 1.0))))
    return f(Cb)


def _alpha(step: PlanStep, sl: tuple, dtype: torch.dtype, grad: bool) -> Alpha:
    """α = alpha × mask × opacity for the slice; a number when it is one, None when opaque. A dissolve layer's
    α is its dissolve pattern (``blend.dissolve_alpha``, 0 or 1 per pixel of the layer)."""
    if step.opaque:
        return None
    if step.blend == "dissolve":
        a = _effective_alpha(step, sl, dtype, grad)
        ly, lx = sl[-2], sl[-1]
        h, w = ly.stop - ly.start, lx.stop - lx.start
        return dissolve_alpha(a, ly.start, lx.start, h, w, dtype, step.spec.tensors.color.device)
    return _effective_alpha(step, sl, dtype, grad)


def _effective_alpha(step: PlanStep, sl: tuple, dtype: torch.dtype, grad: bool) -> Alpha:
    t, op = step.spec.tensors, step.spec.opacity
    if isinstance(op, Tensor):
        if not (grad and op.requires_grad) and op.ndim == 0:
            op = float(op)
        if isinstance(op, Tensor) and op.dtype != dtype:
            op = op.to(dtype)
    a = None
    for x in (t.alpha, t.mask):
        if x is not None:
            x = x[sl] if x.dtype == dtype else x[sl].to(dtype)
            a = x if a is None else a * x
    if a is None:
        return op
    if isinstance(op, Tensor) or op != 1.0:
        a = a * op
    return a


def _clamp_(region: Tensor, step: PlanStep) -> None:
    if step.clamp_lo and step.clamp_hi:
        region.clamp_(0.0, 1.0)
    elif step.clamp_lo:
        region.clamp_min_(0.0)
    elif step.clamp_hi:
        region.clamp_max_(1.0)


def _clamp(x: Tensor, step: PlanStep) -> Tensor:
    if step.clamp_lo and step.clamp_hi:
        return x.clamp(0.0, 1.0)
    if step.clamp_lo:
        return x.clamp_min(0.0)
    if step.clamp_hi:
        return x.clamp_max(1.0)
    return x
