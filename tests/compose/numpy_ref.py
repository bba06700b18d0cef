"""An independent numpy float64 compositor for the compose tests, written from the W3C formulas only.

It reads ``RenderLayerSpec`` fields but none of the compositor's code: the plain loop, one layer at a
time, every layer evaluated (no culling, no bands, no fast paths), clamping after every blend when
asked. W3C Compositing Level 1 for an opaque backdrop Cb, source Cs, α = alpha × mask × opacity:

    normal    Cb + α(Cs − Cb)
    multiply  Cb + α(Cb·Cs − Cb)
    screen    Cb + α(Cs − Cb·Cs)
    plus      Cb + α·Cs
    others    Cb + α(B(Cb, Cs) − Cb), B of W3C section 10 (``W3C_B`` below, written from the spec's
              pseudo-code: branches with ``if``-like selects, SetSat by sorting the channels), and of
              Photoshop's other modes (``PHOTOSHOP_B``: the formulas psd-tools pins against Photoshop)
    dissolve  normal with α replaced by 1 where u(x, y) < α, else 0 (``dissolve_u``: the documented hash,
              rewritten here in numpy uint64 arithmetic)
"""

from __future__ import annotations

import numpy as np
import torch


def _hard_light(cb, cs):
    return np.where(cs <= 0.5, cb * 2 * cs, cb + (2 * cs - 1) - cb * (2 * cs - 1))


def _color_dodge(cb, cs):
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.minimum(1.0, cb / (1.0 - cs))
    return np.where(cb == 0, 0.0, np.where(cs >= 1, 1.0, q))


def _color_burn(cb, cs):
    with np.errstate(divide="ignore", invalid="ignore"):
        q = 1.0 - np.minimum(1.0, (1.0 - cb) / cs)
    return np.where(cb == 1, 1.0, np.where(cs <= 0, 0.0, q))


def _soft_light(cb, cs):
    with np.errstate(invalid="ignore"):
        d = np.where(cb <= 0.25, ((16 * cb - 12) * cb + 4) * cb, np.sqrt(cb))
    return np.where(cs <= 0.5, cb - (1 - 2 * cs) * cb * (1 - cb), cb + (2 * cs - 1) * (d - cb))


# Non-separable (W3C section 10.3); colours are (..., 3, h, w), channel axis -3.
def lum(c):
    return 0.3 * c[..., 0:1, :, :] + 0.59 * c[..., 1:2, :, :] + 0.11 * c[..., 2:3, :, :]


def clip_color(c):
    L, n, x = lum(c), c.min(axis=-3, keepdims=True), c.max(axis=-3, keepdims=True)
    # L − n = 0 (or x − L = 0) only for a gray C = L, where the spec's (C − L)·… is 0·(…/0): its limit keeps C.
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where((n < 0) & (L - n > 0), L + (c - L) * L / (L - n), c)
        return np.where((x > 1) & (x - L > 0), L + (c - L) * (1 - L) / (x - L), c)


def set_lum(c, l):  # noqa: E741
    return clip_color(c + (l - lum(c)))


def sat(c):
    return c.max(axis=-3, keepdims=True) - c.min(axis=-3, keepdims=True)


def set_sat(c, s):
    """The spec's sorted form: Cmax = s, Cmid scaled, Cmin = 0 (or all 0 when Cmax = Cmin)."""
    order = np.argsort(c, axis=-3, kind="stable")
    srt = np.take_along_axis(c, order, axis=-3)
    cmin, cmid, cmax = srt[..., 0:1, :, :], srt[..., 1:2, :, :], srt[..., 2:3, :, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        mid = np.where(cmax > cmin, (cmid - cmin) * s / (cmax - cmin), 0.0)
    new = np.concatenate([np.zeros_like(mid), mid, np.where(cmax > cmin, s, 0.0) + 0 * mid], axis=-3)
    out = np.empty_like(new)
    np.put_along_axis(out, order, new, axis=-3)
    return out


W3C_B = {
    "normal": lambda cb, cs: cs,
    "multiply": lambda cb, cs: cb * cs,
    "screen": lambda cb, cs: cb + cs - cb * cs,
    "overlay": lambda cb, cs: _hard_light(cs, cb),
    "darken": np.minimum,
    "lighten": np.maximum,
    "color-dodge": _color_dodge,
    "color-burn": _color_burn,
    "hard-light": _hard_light,
    "soft-light": _soft_light,
    "difference": lambda cb, cs: np.abs(cb - cs),
    "exclusion": lambda cb, cs: cb + cs - 2 * cb * cs,
    "hue": lambda cb, cs: set_lum(set_sat(cs, sat(cb)), lum(cb)),
    "saturation": lambda cb, cs: set_lum(set_sat(cb, sat(cs)), lum(cb)),
    "color": lambda cb, cs: set_lum(cs, lum(cb)),
    "luminosity": lambda cb, cs: set_lum(cb, lum(cs)),
}


def _vivid_light(cb, cs):
    with np.errstate(divide="ignore", invalid="ignore"):
        burn = 1.0 - np.minimum(1.0, (1.0 - cb) / (2.0 * cs))
        dodge = np.minimum(1.0, cb / (2.0 * (1.0 - cs)))
    out = np.where(cs <= 0.5, burn, dodge)
    return np.where(cs <= 0.0, 0.0, np.where(cs >= 1.0, 1.0, out))


def _divide(cb, cs):
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.minimum(1.0, cb / cs)
    return np.where(cs <= 0.0, np.where(cb > 0.0, 1.0, 0.0), q)


def _pick_pixel(cond):
    def choose(cb, cs):
        cb, cs = np.broadcast_arrays(cb, cs)
        return np.where(cond(lum(cs), lum(cb)), cs, cb)

    return choose


# Photoshop's other modes (psd-tools' composite/blend.py, pinned there against Photoshop's own renders).
PHOTOSHOP_B = {
    "linear-burn": lambda cb, cs: np.maximum(0.0, cb + cs - 1.0),
    "linear-dodge": lambda cb, cs: np.minimum(1.0, cb + cs),
    "subtract": lambda cb, cs: np.maximum(0.0, cb - cs),
    "divide": _divide,
    "vivid-light": _vivid_light,
    "linear-light": lambda cb, cs: np.where(
        cs > 0.5, np.minimum(1.0, cb + 2 * cs - 1), np.maximum(0.0, cb + 2 * cs - 1)
    ),
    "pin-light": lambda cb, cs: np.where(cs > 0.5, np.maximum(cb, 2 * cs - 1), np.minimum(cb, 2 * cs)),
    # the tie Cb + Cs = 1 (8-bit codes a + b = 255) taken to 2^-20, as the package documents
    "hard-mix": lambda cb, cs: np.where(
        np.abs(cb + cs - 1) <= 2.0**-20, np.where(cb > 0.5, 1.0, 0.0), np.where(cb + cs > 1, 1.0, 0.0)
    ),
    "darker-color": _pick_pixel(lambda ls, lb: ls < lb),
    "lighter-color": _pick_pixel(lambda ls, lb: ls > lb),
    "dissolve": lambda cb, cs: cs + 0 * cb,
}
W3C_B.update(PHOTOSHOP_B)
NON_SEPARABLE = ("hue", "saturation", "color", "luminosity", "darker-color", "lighter-color")


def dissolve_u(h: int, w: int, y0: int = 0, x0: int = 0) -> np.ndarray:
    """u(x, y) of dissolve for layer pixels rows y0:y0+h, columns x0:x0+w, (1, h, w) float64: the 32-bit hash
    of lasagna.compose.blend's docstring (x·73856093 ⊕ y·19349663 ⊕ 0x2545F491, then twice h ^= h >> 16,
    h = h·0x045D9F3B mod 2^32, then h ^= h >> 16), top 24 bits / 2^24."""
    M = np.uint64(0xFFFFFFFF)
    y = np.arange(y0, y0 + h, dtype=np.uint64)[:, None]
    x = np.arange(x0, x0 + w, dtype=np.uint64)[None, :]
    v = ((x * np.uint64(73856093)) ^ (y * np.uint64(19349663)) ^ np.uint64(0x2545F491)) & M
    for _ in range(2):
        v = v ^ (v >> np.uint64(16))
        v = (v * np.uint64(0x045D9F3B)) & M
    v = v ^ (v >> np.uint64(16))
    return ((v >> np.uint64(8)).astype(np.float64) / 2.0**24)[None]


def _w3c(name):
    def formula(cb, cs, a):
        cb3, cs3 = (np.broadcast_to(x, (*x.shape[:-3], 3, *x.shape[-2:])) for x in (cb, cs))
        if name in NON_SEPARABLE:
            b = W3C_B[name](*np.broadcast_arrays(cb3, cs3))
            b = b if cb.shape[-3] == 3 else b[..., :1, :, :]
        else:
            b = W3C_B[name](cb, cs)
        return cb + a * (b - cb)

    return formula


def _dissolve(cb, cs, a):
    """Normal with α → [u < α], the pattern anchored at the top-left pixel (idempotent on α ∈ {0, 1})."""
    h, w = np.broadcast_shapes(np.shape(cb), np.shape(cs))[-2:]
    a = (dissolve_u(h, w) < a).astype(np.float64)
    return cb + a * (cs - cb)


FORMULAS = {
    "normal": lambda cb, cs, a: cb + a * (cs - cb),
    "multiply": lambda cb, cs, a: cb + a * (cb * cs - cb),
    "screen": lambda cb, cs, a: cb + a * (cs - cb * cs),
    "plus": lambda cb, cs, a: cb + a * cs,
    **{name: _w3c(name) for name in W3C_B if name not in ("normal", "multiply", "screen", "dissolve")},
    "dissolve": _dissolve,
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
        if spec.blend == "dissolve":
            al = (dissolve_u(y1 - y0, x1 - x0, y0 - y, x0 - x) < al).astype(np.float64)
        res = FORMULAS[spec.blend](cb, cs, al)
        out[:, y0:y1, x0:x1] = np.clip(res, 0.0, 1.0) if clamp == "layer" else res
    if clamp == "output":
        out = np.clip(out, 0.0, 1.0)
    if linear:
        out = encode(out)
    return out
