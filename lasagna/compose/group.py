"""Groups: compositing onto a backdrop with alpha, isolated and pass-through groups (W3C Compositing Level 1).

The top-level canvas is opaque, so ``blend.py``'s kernels are the spec's formulas for αb = 1. Inside an
isolated group the backdrop starts fully transparent (section 8.2 "Isolated Groups"), and a layer is
composited onto a backdrop of colour ``Cb`` and alpha ``αb`` by the general formula (section 6
"General Formula for Compositing and Blending", with source-over, section 5.1):

    Cr = (1 − αb)·Cs + αb·B(Cb, Cs)          the blend, modulated by the backdrop's alpha (section 10)
    co = αs·Cr + (1 − αs)·cb                  source-over on premultiplied colour, cb = αb·Cb
    αo = αs + (1 − αs)·αb

and ``plus`` by Porter–Duff lighter (section 9.1): co = αs·Cs + cb, αo = min(1, αs + αb). Such a canvas is
kept premultiplied, ``State = (c, α)``: its colour is then defined where α = 0 too (c = 0), and the
unpremultiplied Cb = c / α that B needs is only read where it is weighted by α (``UNPREMULTIPLY_EPS``).
An opaque canvas is ``State = (C, None)``, on which every formula above reduces to ``blend.py``'s kernel.

An isolated group's children are composited onto ``(0, 0)``; its result ``(cg, αg)`` is then one layer of
colour ``Cg = cg / αg`` and alpha ``αg × mask × opacity``, blended onto the group backdrop with the group's
blend. A pass-through group's children are composited onto the group backdrop itself (a non-isolated group,
section 8: the initial backdrop is the group backdrop), and the group's ``mask × opacity`` α mixes the result
``Sn`` with the backdrop ``Sb``: ``Sb + α(Sn − Sb)`` (on both c and α when the backdrop has alpha). Over an
opaque backdrop that is exactly the PDF/W3C non-isolated group of blend normal: the backdrop removed from the
group's result and the group composited back with opacity α give Cb + α(Cn − Cb).

A clipping chain (``spec.clip``, Photoshop's clipping mask) is an isolated group whose first child is the base:
the clipped layers are composited onto the base's result ``(cb, αb)`` by the same general formula, and the chain
is one layer of colour ``c / α`` and the base's alpha αb × mask × opacity. That is psd-tools' model (its
``_apply_clip_layers`` seeds a compositor with the base's colour and alpha and keeps the base's alpha), which it
pins against Photoshop's merged images.

An adjustment layer (``spec.adjust``) changes the colour under it and keeps its alpha: over ``(c, αb)`` the colour
``Cb = c / αb`` becomes ``Cb + α(B(Cb, f(Cb)) − Cb)`` (psd-tools' ``_apply_adjustment``), premultiplied again.

Clamping (``clamp="layer"``): after each child the premultiplied colour is clamped to [0, α] (the colour to
[0, 1]), and an isolated group's colour after it is blended. Everything here is pure functions, so autograd
differentiates through groups (``render`` uses the recorded engine for a tail with groups).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from lasagna.compose.blend import KERNELS, LERP_B, Alpha, broadcast_shape, dissolve_alpha
from lasagna.compose.plan import PlanStep, RenderPlan
from lasagna.compose.step import _adjusted, _alpha, _clamp, _color
from lasagna.numerics import UNPREMULTIPLY_EPS

State = tuple[Tensor, Tensor | None]  # (C, None) opaque, or premultiplied (c, α)

# B(Cb, Cs) of every mode but plus (W3C section 10.1 and 10.2; blend.py's for the lerp-computed modes, Photoshop's
# included: over a backdrop with alpha they take the same general formula).
MIX: dict[str, Callable[[Tensor, Tensor], Tensor]] = {
    "normal": lambda Cb, Cs: Cs,
    "multiply": lambda Cb, Cs: Cb * Cs,
    "screen": lambda Cb, Cs: Cb + Cs - Cb * Cs,
    **LERP_B,
}


def unpremultiply(c: Tensor, a: Tensor) -> Tensor:
    """C = c / α (W3C section 5.1, "Co = co / αo"), 0 where α = 0 (there c = 0)."""
    return c / a.clamp_min(UNPREMULTIPLY_EPS)


def composite_over(c: Tensor, ab: Tensor, Cs: Tensor, a: Alpha, blend: str) -> tuple[Tensor, Tensor]:
    """A source ``Cs`` with alpha ``a`` (None: 1) blended with ``blend`` onto the premultiplied backdrop
    ``(c, ab)``: the general formula of W3C section 6 (module docstring). Returns ``(co, αo)``."""
    if blend == "plus":  # Porter–Duff lighter, section 9.1: co = αs·Cs + cb, αo = αs + αb (≤ 1)
        co = c + Cs if a is None else c + Cs * a
        return co, (ab + (1.0 if a is None else a)).clamp_max(1.0)
    Cr = Cs
    if blend != "normal":  # B(Cb, Cs) = Cs for normal: Cr = Cs
        Cr = Cs + ab * (MIX[blend](unpremultiply(c, ab), Cs) - Cs)  # (1 − αb)·Cs + αb·B(Cb, Cs)
    if a is None:
        return Cr.expand(broadcast_shape(c.shape, Cr.shape)), torch.ones_like(ab)
    return c + a * (Cr - c), ab + a * (1.0 - ab)


def blend_state(state: State, blend: str, Cs: Tensor, a: Alpha) -> State:
    """``Cs`` with alpha ``a`` blended onto ``state``: ``blend.py``'s kernel over an opaque one."""
    C, ab = state
    if ab is None:
        return KERNELS[blend](C, Cs, a), None
    return composite_over(C, ab, Cs, a, blend)


def adjust_state(state: State, step: PlanStep, a: Alpha, dtype: torch.dtype) -> State:
    """Adjustment layer ``step`` over ``state``: the colour Cb becomes Cb + α(B(Cb, f(Cb)) − Cb) and the alpha is
    kept (psd-tools' ``_apply_adjustment``: an adjustment has no coverage of its own)."""
    C, ab = state
    if ab is None:
        return KERNELS[step.blend](C, _adjusted(step, C, dtype), a), None
    Cb = unpremultiply(C, ab)
    return KERNELS[step.blend](Cb, _adjusted(step, Cb, dtype), a) * ab, ab


def clamp_state(state: State, step: PlanStep) -> State:
    """The clamp after ``step`` (``clamp="layer"``): the colour to [0, 1], i.e. a premultiplied c to [0, α]."""
    C, ab = state
    if ab is None:
        return _clamp(C, step), None
    if step.clamp_lo or step.clamp_hi:
        return torch.minimum(C.clamp_min(0.0), ab), ab
    return state


def apply_group(
    plan: RenderPlan, step: PlanStep, backdrop: Tensor, y0: int, y1: int, dtype: torch.dtype, grad: bool
) -> Tensor:
    """The opaque canvas under group ``step``'s rectangle, rows ``y0:y1`` (``backdrop``), after the group
    (before its clamp, which the caller applies)."""
    return group_state(step, (backdrop, None), (y0, y1, step.x0, step.x1), dtype, grad)[0]


def _mask_alpha(step: PlanStep, rect: tuple[int, int, int, int], dtype: torch.dtype, grad: bool) -> Alpha:
    """The group's mask × opacity over canvas ``rect``; None when it is exactly 1."""
    spec, (y0, y1, x0, x1) = step.spec, rect
    op = spec.opacity
    if isinstance(op, Tensor):
        op = op.to(dtype) if (grad and op.requires_grad) or op.ndim else float(op)
    if spec.mask is None:
        return None if not isinstance(op, Tensor) and op == 1.0 else op
    ly, lx = step.ly0 + y0 - step.y0, step.lx0 + x0 - step.x0
    m = spec.mask[..., ly : ly + (y1 - y0), lx : lx + (x1 - x0)].to(dtype)
    return m if not isinstance(op, Tensor) and op == 1.0 else m * op


def group_state(step: PlanStep, state: State, rect: tuple[int, int, int, int], dtype: torch.dtype, grad: bool) -> State:
    """``state`` (the canvas over ``rect`` = rows y0:y1, columns x0:x1) after group ``step`` (module docstring)."""
    a = _mask_alpha(step, rect, dtype, grad)
    if step.spec.isolated:
        C = state[0]
        shape = (*C.shape[:-3], 3, *C.shape[-2:])
        empty = (C.new_zeros(shape), C.new_zeros((*C.shape[:-3], 1, *C.shape[-2:])))
        kids = step.children or ()
        if step.spec.clip:  # a clipping chain: the clipped layers paint on the base, which keeps its alpha
            base = _children(kids[:1], empty, rect, dtype, grad)
            cg, ag = _children(kids[1:], base, rect, dtype, grad)
            alpha = base[1] if a is None else base[1] * a
        else:
            cg, ag = _children(kids, empty, rect, dtype, grad)
            alpha = ag if a is None else ag * a
        if step.spec.blend == "dissolve":  # the group's pattern, on canvas coordinates (it has no pixels of its own)
            y0, y1, x0, x1 = rect
            alpha = dissolve_alpha(alpha, y0, x0, y1 - y0, x1 - x0, C.dtype, C.device)
        return blend_state(state, step.spec.blend, unpremultiply(cg, ag), alpha)
    after = _children(step.children or (), state, rect, dtype, grad)
    if a is None:
        return after
    mixed = tuple(None if s is None else s + a * (n - s) for s, n in zip(state, after))
    return mixed  # type: ignore[return-value]


def _children(
    children: tuple[PlanStep, ...], state: State, rect: tuple[int, int, int, int], dtype: torch.dtype, grad: bool
) -> State:
    """``state`` after each live step of ``children`` in turn, each on its part of ``rect``."""
    y0, y1, x0, x1 = rect
    C, ab = state
    for child in children:
        cy0, cy1, cx0, cx1 = max(child.y0, y0), min(child.y1, y1), max(child.x0, x0), min(child.x1, x1)
        if cy0 >= cy1 or cx0 >= cx1:
            continue
        region = (..., slice(cy0 - y0, cy1 - y0), slice(cx0 - x0, cx1 - x0))
        sub: State = (C[region], None if ab is None else ab[region])
        if child.children is not None:
            new = group_state(child, sub, (cy0, cy1, cx0, cx1), dtype, grad)
        else:
            ly, lx = child.ly0 + cy0 - child.y0, child.lx0 + cx0 - child.x0
            sl = (..., slice(ly, ly + (cy1 - cy0)), slice(lx, lx + (cx1 - cx0)))
            a = _alpha(child, sl, dtype, grad)
            if child.spec.adjust is not None:
                new = adjust_state(sub, child, a, dtype)
            else:
                new = blend_state(sub, child.blend, _color(child, sl, dtype, grad), a)
        new = clamp_state(new, child)
        if (cy0, cy1, cx0, cx1) == rect:
            C, ab = new
        else:  # a fresh copy: the previous canvas may be saved for backward
            C = _assign(C, region, new[0])
            ab = None if ab is None else _assign(ab, region, new[1])  # type: ignore[arg-type]
    return C, ab


def _assign(whole: Tensor, region: tuple, part: Tensor) -> Tensor:
    shape = broadcast_shape(whole.shape, (*part.shape[:-2], *whole.shape[-2:]))
    out = whole.expand(shape).clone()
    out[region] = part
    return out
