"""An independent numpy float64 compositor for the compose tests, written from the W3C formulas only.

It reads ``RenderLayerSpec`` fields but none of the compositor's code: the plain loop, one layer at a
time, every layer evaluated (no culling, no bands, no fast paths), clamping after every blend when
asked. W3C Compositing Level 1 for an opaque backdrop Cb, source Cs, α = alpha × mask × opacity:

    normal    Cb + α(Cs − Cb)
    multiply  Cb + α(Cb·Cs − Cb)
    screen    Cb + α(Cs − Cb·Cs)
    plus      Cb + α·Cs
"""

from __future__ import annotations

import numpy as np
import torch

FORMULAS = {
    "normal": lambda cb, cs, a: cb + a * (cs - cb),
    "multiply": lambda cb, cs, a: cb + a * (cb * cs - cb),
    "screen": lambda cb, cs, a: cb + a * (cs - cb * cs),
    "plus": lambda cb, cs, a: cb + a * cs,
}


def decode(c: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decode, extended odd-symmetrically (CSS Color 4)."""
    a = np.abs(c)
    return np.sign(c) * np.where(a <= 0.04045, a / 12.92, ((a + 0.055) / 1.055) ** 2.4)


def encode(c: np.ndarray) -> np.ndarray:
    a = np.abs(c)
    return np.sign(c) * np.where(a <= 0.0031308, a * 12.92, 1.055 * a ** (1 / 2.4) - 0.055)


def np64(t: torch.Tensor | None) -> np.ndarray | None:
    return None if t is None else t.detach().to(torch.float64).cpu().numpy()


def composite(layers, canvas, background=(0.0, 0.0, 0.0), blend_space="srgb", clamp="layer") -> np.ndarray:
    """(3, H, W) float64 composite of unbatched ``RenderLayerSpec``s (bottom to top)."""
    H, W = canvas
    linear = blend_space == "linear"
    out = np.empty((3, H, W))
    bg = np.asarray(background, dtype=np.float64)
    out[:] = (decode(bg) if linear else bg)[:, None, None]
    for spec in layers:
        if not spec.visible:
            continue
        color = np64(spec.tensors.color)
        h, w = color.shape[-2:]
        color = np.broadcast_to(color, (3, h, w))
        if linear and spec.encoded and spec.blend != "multiply":
            color = decode(color)
        a = np.ones((1, h, w))
        for extra in (spec.tensors.alpha, spec.tensors.mask):
            if extra is not None:
                a = a * np64(extra)
        op = spec.opacity
        a = a * (float(op.detach()) if isinstance(op, torch.Tensor) else float(op))
        x, y = spec.offset
        x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + w, W), min(y + h, H)
        if x0 >= x1 or y0 >= y1:
            continue
        cb = out[:, y0:y1, x0:x1]
        cs = color[:, y0 - y : y1 - y, x0 - x : x1 - x]
        al = a[:, y0 - y : y1 - y, x0 - x : x1 - x]
        res = FORMULAS[spec.blend](cb, cs, al)
        out[:, y0:y1, x0:x1] = np.clip(res, 0.0, 1.0) if clamp == "layer" else res
    if clamp == "output":
        out = np.clip(out, 0.0, 1.0)
    if linear:
        out = encode(out)
    return out
