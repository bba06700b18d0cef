"""An independent float64 reference compositor for stack folders, used as a judge would use theirs.

Written from the formulas of docs/ARCHITECTURE.md only; it imports nothing from ``lasagna``. It reads
stack.json with ``json`` and every PNG with pypng (the package reads ≤ 8-bit PNGs with Pillow), and
composes with numpy in float64, one layer at a time, the plain way:

W3C Compositing Level 1 for an opaque backdrop Cb, source Cs, α = alpha × mask × opacity:
    normal    Cb + α(Cs − Cb)
    multiply  Cb + α(Cb·Cs − Cb)      (a 1-channel multiplier broadcasts over RGB)
    screen    Cb + α(Cs − Cb·Cs)
    plus      Cb + α·Cs
    others    Cb + α(B(Cb, Cs) − Cb), B of W3C section 10 and of Photoshop's other modes
              (``tests/compose/numpy_ref.py``'s ``W3C_B``); dissolve: α → [u(x, y) < α] (``dissolve_u``, on the
              layer's pixel coordinates; a group's on the canvas's)
Groups: W3C section 8 (see ``composite_reference``).
Stored PNG values v map to y = lo + (hi − lo)·v (alpha never). ``blend_space="linear"`` decodes colour
values (background, solid colours, normal/plus/screen sources) from sRGB, never multiply factors, and
encodes the result back. ``clamp="layer"`` clamps to [0, 1] after every blend, ``"output"`` once.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import png

from tests.adjust_ref import adjust_reference
from tests.compose.numpy_ref import W3C_B, dissolve_u

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

    Layers that are hidden, or learned without a ``source``, are not composed. Groups (``kind: group``)
    follow W3C Compositing Level 1, section 8: an isolated group composites its layers onto a transparent
    canvas (with the spec's general formula, non-premultiplied: αo = αs + αb(1 − αs), αo·Co = αs(1 − αb)Cs
    + αs·αb·B(Cb, Cs) + (1 − αs)·αb·Cb; plus: αo·Co = αs·Cs + αb·Cb, αo = min(1, αs + αb)) and is then one
    layer of that colour and alpha × mask × opacity; a pass-through group composites its layers onto the
    canvas and mixes the result with what was there by mask × opacity. A group's offset moves its layers
    and its mask (0 outside the mask).
    """
    folder = Path(folder)
    doc = json.loads((folder / "stack.json").read_text())
    W, H = doc["canvas"]["width"], doc["canvas"]["height"]
    linear = doc.get("blend_space", "srgb") == "linear"
    ctx = (folder, W, H, linear, doc.get("clamp", "layer") == "layer")
    decode = srgb_to_linear if linear else (lambda c: c)

    bg = np.asarray(doc["canvas"].get("background", [0.0, 0.0, 0.0]), dtype=np.float64)
    out = np.empty((3, H, W))
    out[:] = decode(bg)[:, None, None]
    out, _ = _compose(doc["layers"], out, None, (0, 0), ctx)
    if linear:
        out = linear_to_srgb(out)
    return np.clip(out, 0.0, 1.0)


def composite_reference_rgba(folder: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(straight colour (3, H, W), alpha (1, H, W)) float64 of a stack folder; a document without a background
    (``background`` null) starts from transparency (colour 0, alpha 0) and keeps its alpha, any other is opaque."""
    folder = Path(folder)
    doc = json.loads((folder / "stack.json").read_text())
    if doc["canvas"].get("background", [0.0, 0.0, 0.0]) is not None:
        out = composite_reference(folder)
        return out, np.ones((1, *out.shape[1:]))
    W, H = doc["canvas"]["width"], doc["canvas"]["height"]
    linear = doc.get("blend_space", "srgb") == "linear"
    ctx = (folder, W, H, linear, doc.get("clamp", "layer") == "layer")
    out, A = _compose(doc["layers"], np.zeros((3, H, W)), np.zeros((1, H, W)), (0, 0), ctx)
    if linear:
        out = linear_to_srgb(np.clip(out, 0.0, 1.0))
    return np.clip(out, 0.0, 1.0), A


def _offset(layer: dict, origin: tuple[int, int]) -> tuple[int, int]:
    off = layer.get("offset", {})
    return off.get("x", 0) + origin[0], off.get("y", 0) + origin[1]


def _read_mask(folder: Path, rel: str) -> np.ndarray:
    m, m_alpha = read_png64(folder / rel)
    return m[:1] * (1.0 if m_alpha is None else m_alpha)


def _B(blend: str, cb: np.ndarray, cs: np.ndarray) -> np.ndarray:
    cs = np.broadcast_to(cs, cb.shape)
    return {"normal": lambda: cs, "multiply": lambda: cb * cs, "screen": lambda: cb + cs - cb * cs}.get(
        blend, lambda: W3C_B[blend](cb, np.ascontiguousarray(cs))
    )()


def _over(C, A, Cs, As, blend):
    """Source (Cs, As) onto a canvas (C, A) with alpha: the spec's general formula (see composite_reference)."""
    if blend == "plus":
        ao, premul = np.minimum(1.0, As + A), As * Cs + A * C
    else:
        ao = As + A * (1 - As)
        premul = As * (1 - A) * Cs + As * A * _B(blend, C, Cs) + (1 - As) * A * C
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(ao > 0, premul / np.where(ao > 0, ao, 1.0), 0.0), ao


def _compose(layers, out, A, origin, ctx):
    """``layers`` onto the canvas ``out`` (3, H, W), opaque when ``A`` is None, else of alpha ``A`` (1, H, W)."""
    folder, W, H, linear, clamp_each = ctx
    decode = srgb_to_linear if linear else (lambda c: c)
    for layer in layers:
        if not layer.get("visible", True):
            continue
        blend = ALIASES.get(layer.get("blend", "normal"), layer.get("blend", "normal"))
        kind = layer["kind"]
        x, y = _offset(layer, origin)
        if kind == "group":
            m = np.full((1, H, W), layer.get("opacity", 1.0))
            if layer.get("mask"):
                mask = _read_mask(folder, layer["mask"])
                placed = np.zeros((1, H, W))
                mh, mw = mask.shape[1:]
                x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + mw, W), min(y + mh, H)
                if x0 < x1 and y0 < y1:
                    placed[:, y0:y1, x0:x1] = mask[:, y0 - y : y1 - y, x0 - x : x1 - x]
                m = m * placed
            A0 = np.ones((1, H, W)) if A is None else A
            if layer.get("isolated", False):
                Cg, Ag = _compose(layer.get("layers", []), np.zeros((3, H, W)), np.zeros((1, H, W)), (x, y), ctx)
                ag = Ag * m
                if blend == "dissolve":
                    ag = (dissolve_u(H, W) < ag).astype(np.float64)
                res, ao = _over(out, A0, Cg, ag, blend)
                res = np.clip(res, 0.0, 1.0) if clamp_each else res
            else:
                Cn, An = _compose(layer.get("layers", []), out.copy(), None if A is None else A.copy(), (x, y), ctx)
                An = np.ones((1, H, W)) if An is None else An
                ao = A0 + m * (An - A0)
                premul = A0 * out + m * (An * Cn - A0 * out)
                with np.errstate(divide="ignore", invalid="ignore"):
                    res = np.where(ao > 0, premul / np.where(ao > 0, ao, 1.0), 0.0)
            out, A = res, (None if A is None else ao)
            continue
        if kind == "adjustment":  # f of the (encoded) colour below, mixed by mask × opacity; alpha kept
            m = np.full((1, H, W), layer.get("opacity", 1.0))
            if layer.get("mask"):
                mask = _read_mask(folder, layer["mask"])
                placed = np.zeros((1, H, W))
                mh, mw = mask.shape[1:]
                x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + mw, W), min(y + mh, H)
                if x0 < x1 and y0 < y1:
                    placed[:, y0:y1, x0:x1] = mask[:, y0 - y : y1 - y, x0 - x : x1 - x]
                m = m * placed
            encoded = linear_to_srgb(np.clip(out, 0, 1)) if linear else out
            cs = decode(adjust_reference(layer["adjustment"], encoded))
            res = out + m * (_B(blend, out, cs) - out)
            out = np.clip(res, 0.0, 1.0) if clamp_each else res
            continue
        lo, hi = layer.get("range", [0.0, 1.0])
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
            a = a * _read_mask(folder, layer["mask"])

        # Intersection of the layer's rectangle with the canvas.
        x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + w, W), min(y + h, H)
        if x0 >= x1 or y0 >= y1:
            continue
        cb = out[:, y0:y1, x0:x1]
        cs = color[:, y0 - y : y1 - y, x0 - x : x1 - x]
        al = a[:, y0 - y : y1 - y, x0 - x : x1 - x]
        if blend == "dissolve":
            al = (dissolve_u(y1 - y0, x1 - x0, y0 - y, x0 - x) < al).astype(np.float64)
        if A is not None:  # inside an isolated group: the canvas has alpha
            res, A[:, y0:y1, x0:x1] = _over(cb, A[:, y0:y1, x0:x1], cs, al, blend)
        elif blend == "normal":
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
    return out, A


def to_uint8(image: np.ndarray) -> np.ndarray:
    """(3, H, W) float in [0, 1] -> (H, W, 3) uint8, rounded to nearest."""
    return np.rint(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8).transpose(1, 2, 0)
