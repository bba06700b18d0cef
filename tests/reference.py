"""An independent float64 reference compositor for stack folders, used as a judge would use theirs.

Written from the formulas of docs/ARCHITECTURE.md only; it imports nothing from ``lasagna``. It reads
stack.json with ``json`` and every PNG with pypng (the package reads ≤ 8-bit PNGs with Pillow), and
composes with numpy in float64, one layer at a time, the plain way:

W3C Compositing Level 1 for an opaque backdrop Cb, source Cs, α = alpha × mask × opacity:
    normal    Cb + α(Cs − Cb)
    multiply  Cb + α(Cb·Cs − Cb)      (a 1-channel multiplier broadcasts over RGB)
    screen    Cb + α(Cs − Cb·Cs)
    plus      Cb + α·Cs
    others    Cb + α(B(Cb, Cs) − Cb), B of W3C section 10 (``tests/compose/numpy_ref.py``'s ``W3C_B``)
Stored PNG values v map to y = lo + (hi − lo)·v (alpha never). ``blend_space="linear"`` decodes colour
values (background, solid colours, normal/plus/screen sources) from sRGB, never multiply factors, and
encodes the result back. ``clamp="layer"`` clamps to [0, 1] after every blend, ``"output"`` once.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import png

from tests.compose.numpy_ref import W3C_B

ALIASES = {"alpha-linear": "normal", "multiply-luminosity": "multiply", "additive": "plus"}


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 decode, extended odd-symmetrically below 0 (sign(c)·f(|c|))."""
    a = np.abs(c)
    out = np.where(a <= 0.04045, a / 12.92, ((a + 0.055) / 1.055) ** 2.4)
    return np.sign(c) * out


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 encode, extended odd-symmetrically below 0."""
    a = np.abs(c)
    out = np.where(a <= 0.0031308, a * 12.92, 1.055 * a ** (1 / 2.4) - 0.055)
    return np.sign(c) * out


def read_png64(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(C, h, w) float64 colour with C ∈ {1, 3}, and (1, h, w) alpha or None, via pypng."""
    w, h, rows, info = png.Reader(filename=str(path)).asDirect()
    planes = info["planes"]
    arr = np.array([np.asarray(r, dtype=np.float64) for r in rows]).reshape(h, w, planes)
    arr /= 2 ** info["bitdepth"] - 1
    chw = arr.transpose(2, 0, 1)
    if info["alpha"]:
        return chw[:-1], chw[-1:]
    return chw, None


def composite_reference(folder: str | Path) -> np.ndarray:
    """The composite of the stack in ``folder`` as float64 (3, H, W) in [0, 1] (clamped, not quantised).

    Layers that are hidden, or learned without a ``source``, are not composed.
    """
    folder = Path(folder)
    doc = json.loads((folder / "stack.json").read_text())
    W, H = doc["canvas"]["width"], doc["canvas"]["height"]
    linear = doc.get("blend_space", "srgb") == "linear"
    clamp_each = doc.get("clamp", "layer") == "layer"
    decode = srgb_to_linear if linear else (lambda c: c)

    bg = np.asarray(doc["canvas"].get("background", [0.0, 0.0, 0.0]), dtype=np.float64)
    out = np.empty((3, H, W))
    out[:] = decode(bg)[:, None, None]

    for layer in doc["layers"]:
        if not layer.get("visible", True):
            continue
        blend = ALIASES.get(layer.get("blend", "normal"), layer.get("blend", "normal"))
        lo, hi = layer.get("range", [0.0, 1.0])
        kind = layer["kind"]
        if kind == "solid":
            rgba = list(layer["color"])
            size = layer.get("size") or {"width": W, "height": H}
            h, w = size["height"], size["width"]
            color = np.empty((3, h, w))
            color[:] = np.asarray(rgba[:3], dtype=np.float64)[:, None, None]
            alpha = np.full((1, h, w), rgba[3] if len(rgba) == 4 else 1.0)
        else:
            if kind == "learned" and not layer.get("source"):
                continue
            color, alpha = read_png64(folder / layer["source"])
            h, w = color.shape[1:]
            if alpha is None:
                alpha = np.ones((1, h, w))
        color = lo + (hi - lo) * color
        if blend != "multiply":
            color = decode(np.broadcast_to(color, (3, h, w)))
        a = alpha * layer.get("opacity", 1.0)
        if layer.get("mask"):
            m, m_alpha = read_png64(folder / layer["mask"])
            a = a * m[:1] * (1.0 if m_alpha is None else m_alpha)

        x, y = layer.get("offset", {}).get("x", 0), layer.get("offset", {}).get("y", 0)
        # Intersection of the layer's rectangle with the canvas.
        x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + w, W), min(y + h, H)
        if x0 >= x1 or y0 >= y1:
            continue
        cb = out[:, y0:y1, x0:x1]
        cs = color[:, y0 - y : y1 - y, x0 - x : x1 - x]
        al = a[:, y0 - y : y1 - y, x0 - x : x1 - x]
        if blend == "normal":
            res = cb + al * (cs - cb)
        elif blend == "multiply":
            res = cb + al * (cb * cs - cb)
        elif blend == "screen":
            res = cb + al * (cs - cb * cs)
        elif blend == "plus":
            res = cb + al * cs
        elif blend in W3C_B:
            res = cb + al * (W3C_B[blend](cb, np.broadcast_to(cs, cb.shape)) - cb)
        else:
            raise ValueError(f"unknown blend {blend!r}")
        out[:, y0:y1, x0:x1] = np.clip(res, 0.0, 1.0) if clamp_each else res

    if linear:
        out = linear_to_srgb(out)
    return np.clip(out, 0.0, 1.0)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """(3, H, W) float in [0, 1] -> (H, W, 3) uint8, rounded to nearest."""
    return np.rint(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8).transpose(1, 2, 0)
