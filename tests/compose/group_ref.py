"""An independent numpy float64 compositor of nested groups, written from W3C Compositing Level 1 only.

It shares nothing with ``lasagna.compose.group`` but the spec: every layer is placed on a canvas-size
array (alpha 0 outside its rectangle) and composited with the spec's formula in its *non-premultiplied*
form (section 10, the note under "Blending"), one layer at a time, no culling, no inlining:

    αo = αs + αb·(1 − αs)
    αo·Co = αs·(1 − αb)·Cs + αs·αb·B(Cb, Cs) + (1 − αs)·αb·Cb,   Co = (αo·Co) / αo  (0 where αo = 0)
    plus (Porter–Duff lighter, section 9.1):  αo·Co = αs·Cs + αb·Cb,  αo = min(1, αs + αb)

The top-level canvas is the opaque background (αb = 1: the formulas reduce to the opaque ones of
``numpy_ref.py``). An isolated group (section 8.2) composites its children onto a transparent canvas and
is then one source of colour Cg, alpha αg × mask × opacity. A pass-through group composites its children
onto the canvas itself and mixes: αo = αb + m(αn − αb), αo·Co = αb·Cb + m(αn·Cn − αb·Cb), m = mask × opacity.
``clamp="layer"`` clamps Co to [0, 1] after every layer and every isolated group. Dissolve (Photoshop): αs is
replaced by [u < αs], u of ``numpy_ref.dissolve_u`` on the layer's pixel grid (an isolated group's: the canvas's).
A clipping chain (``clip=True``, psd-tools' model of Photoshop's): children[0] onto a transparent canvas gives
(Cb, αb), the other children are composited onto that, and the chain is one source of their colour and alpha
αb × mask × opacity.
"""

from __future__ import annotations

import numpy as np
import torch

from lasagna.compose.plan import RenderGroupSpec
from tests.compose.numpy_ref import NON_SEPARABLE, W3C_B, decode, dissolve_u, encode, np64


def _B(name: str, cb: np.ndarray, cs: np.ndarray) -> np.ndarray:
    cs3 = np.broadcast_to(cs, cb.shape)
    if name == "normal":
        return cs3
    if name == "multiply":
        return cb * cs3
    if name == "screen":
        return cb + cs3 - cb * cs3
    return W3C_B[name](cb, np.ascontiguousarray(cs3)) if name in NON_SEPARABLE else W3C_B[name](cb, cs3)


def _over(C, A, Cs, As, blend):
    """(C, A) non-premultiplied canvas, source (Cs, As) on the canvas grid → (Co, Ao)."""
    if blend == "plus":
        ao = np.minimum(1.0, As + A)
        premul = As * Cs + A * C
    else:
        ao = As + A * (1 - As)
        premul = As * (1 - A) * Cs + As * A * _B(blend, C, Cs) + (1 - As) * A * C
    with np.errstate(divide="ignore", invalid="ignore"):
        co = np.where(ao > 0, premul / np.where(ao > 0, ao, 1.0), 0.0)
    return co, ao


def _placed(x: np.ndarray, offset, H, W, fill: float) -> np.ndarray:
    """``x`` (C, h, w) on the canvas grid at ``offset``, ``fill`` elsewhere."""
    out = np.full((x.shape[0], H, W), fill)
    ox, oy = offset
    h, w = x.shape[1:]
    y0, y1, x0, x1 = max(oy, 0), min(oy + h, H), max(ox, 0), min(ox + w, W)
    if y0 < y1 and x0 < x1:
        out[:, y0:y1, x0:x1] = x[:, y0 - oy : y1 - oy, x0 - ox : x1 - ox]
    return out


def _opacity(spec) -> float:
    op = spec.opacity
    return float(op.detach()) if isinstance(op, torch.Tensor) else float(op)


def _composite(specs, C, A, origin, ctx):
    H, W, linear, clamp = ctx
    for spec in specs:
        if not spec.visible:
            continue
        offset = (spec.offset[0] + origin[0], spec.offset[1] + origin[1])
        if isinstance(spec, RenderGroupSpec):
            m = np.full((1, H, W), _opacity(spec))
            if spec.mask is not None:
                m = m * _placed(np64(spec.mask), offset, H, W, 0.0)
            if spec.clip:  # psd-tools' clipping: the clipped layers over the base, the base's alpha kept
                Cb, Ab = _composite(spec.children[:1], np.zeros((3, H, W)), np.zeros((1, H, W)), offset, ctx)
                Cg, _ = _composite(spec.children[1:], Cb, Ab, offset, ctx)
                ag = Ab * m
                if spec.blend == "dissolve":
                    ag = (dissolve_u(H, W) < ag).astype(np.float64)
                C, A = _over(C, A, Cg, ag, spec.blend)
                if clamp == "layer":
                    C = np.clip(C, 0, 1)
            elif spec.isolated:
                Cg, Ag = _composite(spec.children, np.zeros((3, H, W)), np.zeros((1, H, W)), offset, ctx)
                ag = Ag * m
                if spec.blend == "dissolve":
                    ag = (dissolve_u(H, W) < ag).astype(np.float64)
                C, A = _over(C, A, Cg, ag, spec.blend)
                if clamp == "layer":
                    C = np.clip(C, 0, 1)
            else:
                Cn, An = _composite(spec.children, C, A, offset, ctx)
                ao = A + m * (An - A)
                premul = A * C + m * (An * Cn - A * C)
                with np.errstate(divide="ignore", invalid="ignore"):
                    C = np.where(ao > 0, premul / np.where(ao > 0, ao, 1.0), 0.0)
                A = ao
            continue
        t = spec.tensors
        color = np64(t.color)
        color = np.broadcast_to(color, (3, *color.shape[1:])) if spec.blend != "multiply" else color
        if linear and spec.encoded and spec.blend != "multiply":
            color = decode(color)
        a = np.ones((1, *color.shape[1:]))
        for extra in (t.alpha, t.mask):
            if extra is not None:
                a = a * np64(extra)
        Cs = _placed(np.broadcast_to(color, (color.shape[0], *a.shape[1:])), offset, H, W, 0.0)
        a = a * _opacity(spec)
        if spec.blend == "dissolve":
            a = (dissolve_u(*a.shape[1:]) < a).astype(np.float64)
        As = _placed(a, offset, H, W, 0.0)
        C, A = _over(C, A, Cs, As, spec.blend)
        if clamp == "layer":
            C = np.clip(C, 0, 1)
    return C, A


def composite(specs, canvas, background=(0.0, 0.0, 0.0), blend_space="srgb", clamp="layer") -> np.ndarray:
    """(3, H, W) float64 composite of unbatched specs (layers and groups, bottom to top)."""
    H, W = canvas
    linear = blend_space == "linear"
    bg = np.asarray(background, dtype=np.float64)
    C = np.empty((3, H, W))
    C[:] = (decode(bg) if linear else bg)[:, None, None]
    C, _ = _composite(specs, C, np.ones((1, H, W)), (0, 0), (H, W, linear, clamp))
    if clamp == "output":
        C = np.clip(C, 0, 1)
    return encode(C) if linear else C


def composite_rgba(specs, canvas, blend_space="srgb", clamp="layer") -> tuple[np.ndarray, np.ndarray]:
    """(straight colour (3, H, W), alpha (1, H, W)) float64 of unbatched specs on a transparent canvas (a document
    without a background: the top level composited as an isolated group's children are, section 8.2)."""
    H, W = canvas
    linear = blend_space == "linear"
    C, A = _composite(specs, np.zeros((3, H, W)), np.zeros((1, H, W)), (0, 0), (H, W, linear, clamp))
    if clamp == "output":
        C = np.clip(C, 0, 1)
    return (encode(C) if linear else C), A
