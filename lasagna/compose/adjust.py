"""Adjustments: one pure function per Photoshop adjustment, ``f(C, p) -> C'`` on colour ``(..., 3, h, w)``.

Every function takes the backdrop's (unpremultiplied, sRGB-encoded) colour and the adjustment's parameters (the
document's ``adjustment`` as a plain dict: numbers, or tensors that may require grad) and returns the adjusted
colour in [0, 1]; ``ADJUSTMENTS`` is the table, keyed by the document's ``type``. The formulas of levels, curves,
hue/saturation (colour ranges included), brightness/contrast, exposure, invert, posterize and threshold are the ones
psd-tools pins against Photoshop's merged images (``psd_tools/composite/adjustments.py``); psd-tools renders none
of channel mixer, color balance, vibrance, black & white, gradient map and photo filter, whose formulas are each
function's docstring's (Photoshop's dialog where it states the arithmetic, GIMP's C code where GIMP mirrors the
dialog, else a stated model). Tone curves are in continuous form:
psd-tools (and Photoshop) first quantise the input to the document's codes and read a 256- or 65536-entry table;
here a tone curve is a ``LUT_SIZE``-entry table read with linear interpolation, so it is differentiable in the
colour and in every parameter that moves it (levels' points and gamma, curve points, brightness, contrast,
exposure; a gradient map's stops). Posterize and threshold are step functions: their gradient is 0; the others are
differentiable in every parameter (black & white and colour ranges piecewise, at their sector and trapezoid kinks).

``Adjustment(type, params)`` checks the parameters once and builds what a render reuses (the tone tables);
``adjustment(C)`` applies it. How an adjustment layer composes (its blend, mask and opacity, the backdrop's alpha
kept) is the engine's (``engine.py``, ``group.py``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from lasagna.compose.blend import _set_lum  # the spec's SetLum (with ClipColor), kept in one place
from lasagna.compose.gradient import interpolate_stops
from lasagna.errors import LasagnaError
from lasagna.limits import MAX_CURVE_POINTS
from lasagna.numerics import ADJUST_POW_EPS

Params = Mapping[str, Any]

# Entries of a tone table (levels, curves, brightness/contrast, exposure): linear interpolation between them is
# within (1/4095)²/8 · max|f''| of the curve, far below a 16-bit step for Photoshop's curves; only a gamma's
# t^(1/γ) near t = 0 bends faster, and there Photoshop's own 8-bit table is coarser still (codes 0 and 1).
LUT_SIZE = 4096

# psd-tools' brightness polynomial, reverse-engineered from Photoshop (its ``_BRIGHTNESS_POLY_A/_R``) and the
# contrast spline's control points (``_CONTRAST_CONTROL_X``, inner points moved ±25/255 per unit of contrast).
_BRIGHTNESS_A = (1.65, -1.0, 1.96, 1.0, 1.0)
_BRIGHTNESS_R = (0.35, 10.0, 0.4, 4.0, 1.25)
_CONTRAST_X = (0.0, 63.0 / 255.0, 191.0 / 255.0, 1.0)
_CONTRAST_DELTA = 25.0 / 255.0
# Exposure works in linear light through this power (psd-tools' approximation of the sRGB TRC).
_EXPOSURE_GAMMA = 2.2
# Saturation > 0 divides by (1 − s + this) (psd-tools' ``_apply_saturation``): +100 % is a large finite gain.
_SATURATION_SLACK = 1e-2


def _number(x: Any) -> Tensor | float:
    return x if isinstance(x, Tensor) else float(x)


def _ramp(like: Tensor) -> Tensor:
    """The table's inputs: ``LUT_SIZE`` values evenly spaced over [0, 1]."""
    return torch.linspace(0.0, 1.0, LUT_SIZE, dtype=like.dtype, device=like.device)


def apply_lut(C: Tensor, lut: Tensor) -> Tensor:
    """Each channel c of ``C (..., 3, h, w)`` through its table ``lut[c]`` (``lut`` (3, N) or (1, N)), read with
    linear interpolation; inputs outside [0, 1] read the end values."""
    n = lut.shape[-1]
    pos = C.clamp(0.0, 1.0) * (n - 1)
    i = pos.detach().floor().clamp_max(n - 2)
    w = pos - i
    i = i.long()
    if lut.shape[0] == 1:
        flat, idx = lut[0], i
    else:
        flat = lut.reshape(-1)
        idx = i + torch.arange(3, device=C.device).view(3, 1, 1) * n
    lo, hi = flat[idx], flat[idx + 1]
    return lo + w * (hi - lo)


def _levels_curve(t: Tensor, p: Params) -> Tensor:
    """One channel's levels on ``t``: (t − black)/(white − black) clamped, t^(1/γ), then out_black…out_white."""
    ib, iw, g = _number(p["in_black"]), _number(p["in_white"]), _number(p["gamma"])
    ob, ow = _number(p["out_black"]), _number(p["out_white"])
    x = ((t - ib) / (iw - ib)).clamp(0.0, 1.0)
    # t^(1/γ) has an infinite slope at 0 for γ > 1: the power is taken of max(x, eps), and 0 stays 0.
    x = torch.where(x > 0, x.clamp_min(ADJUST_POW_EPS) ** (1.0 / g), torch.zeros_like(x))
    return (ob + x * (ow - ob)).clamp(0.0, 1.0)


def natural_spline(xs: Tensor, ys: Tensor, t: Tensor) -> Tensor:
    """The natural cubic spline through ``(xs, ys)`` (xs increasing) at ``t``, held at the end values beyond the
    end points (what psd-tools' scipy ``CubicSpline(bc_type="natural")`` gives on the clamped input)."""
    n = xs.shape[0]
    h = xs[1:] - xs[:-1]
    if n == 2:
        m = torch.zeros_like(xs)
    else:  # second derivatives: M0 = Mn = 0, h_{i-1} M_{i-1} + 2(h_{i-1} + h_i) M_i + h_i M_{i+1} = 6 Δ slopes
        a = torch.zeros(n - 2, n - 2, dtype=xs.dtype, device=xs.device)
        idx = torch.arange(n - 2, device=xs.device)
        a[idx, idx] = 2.0 * (h[:-1] + h[1:])
        a[idx[1:], idx[:-1]] = h[1:-1]
        a[idx[:-1], idx[1:]] = h[1:-1]
        slope = (ys[1:] - ys[:-1]) / h
        inner = torch.linalg.solve(a, 6.0 * (slope[1:] - slope[:-1]))
        zero = xs.new_zeros(1)
        m = torch.cat([zero, inner, zero])
    t = t.clamp(xs[0], xs[-1])
    k = torch.searchsorted(xs[1:-1].detach().contiguous(), t.detach().contiguous(), right=True)
    x0, x1, y0, y1, m0, m1, hk = xs[k], xs[k + 1], ys[k], ys[k + 1], m[k], m[k + 1], h[k]
    u, v = (x1 - t) / hk, (t - x0) / hk
    return u * y0 + v * y1 + ((u**3 - u) * m0 + (v**3 - v) * m1) * hk**2 / 6.0


def _interp(t: Tensor, xp: Tensor, fp: Tensor) -> Tensor:
    """``numpy.interp``: piecewise-linear through (xp, fp) (xp increasing), end values beyond; differentiable."""
    t = t.clamp(xp[0], xp[-1])
    k = torch.searchsorted(xp[1:-1].detach().contiguous(), t.detach().contiguous(), right=True)
    x0, x1 = xp[k], xp[k + 1]
    w = (t - x0) / (x1 - x0).clamp_min(ADJUST_POW_EPS)
    return fp[k] + w * (fp[k + 1] - fp[k])


def levels_lut(t: Tensor, p: Params) -> Tensor:
    """Levels' table (psd-tools' ``apply_levels``): each channel's levels, then the composite channel's."""
    return _two_luts(t, p, _levels_curve)


def _curve(t: Tensor, points: Any) -> Tensor:
    pts = points if isinstance(points, Tensor) else torch.tensor(points, dtype=t.dtype, device=t.device)
    pts = pts.to(t.dtype)
    return natural_spline(pts[:, 0], pts[:, 1], t).clamp(0.0, 1.0)


def curves_lut(t: Tensor, p: Params) -> Tensor:
    """Curves' table (psd-tools' ``apply_curves``): natural cubic splines, each channel's then the composite's."""
    return _two_luts(t, p, _curve)


def _two_luts(t: Tensor, p: Params, curve: Callable[[Tensor, Any], Tensor]) -> Tensor:
    """The (3, N) table of each channel's curve followed by the composite channel's (``rgb``)."""
    per = [curve(t, p[name]) if p.get(name) is not None else t for name in ("red", "green", "blue")]
    lut = torch.stack(per)
    if p.get("rgb") is not None:
        lut = curve(lut, p["rgb"])
    return lut


def _brightness_spline(b: Tensor | float, t: Tensor) -> Tensor:
    a, r = _BRIGHTNESS_A, _BRIGHTNESS_R
    babs = abs(b) if not isinstance(b, Tensor) else b.abs()
    pol = [a[i] * t ** r[i] for i in range(5)]
    h = 0.5 * (babs * (pol[0] + pol[1]) + (1.0 - babs) * (pol[2] + pol[3]) + pol[4])
    return b * t * (1.0 - t) * h


def _brightness_contrast_curve(t: Tensor, p: Params) -> Tensor:
    b, c = _number(p["brightness"]), _number(p["contrast"])
    if p.get("legacy"):
        # Photoshop's legacy brightness/contrast: a shift of brightness/255, then contrast as a linear stretch
        # about mid-gray by 1 + c/100 (c < 0) or 1/(1 − c/100) (c > 0; infinite at 100: a threshold at ½).
        x = t + b / 255.0
        c = torch.as_tensor(c, dtype=t.dtype, device=t.device)
        k = torch.where(c <= 0, 1.0 + c / 100.0, 1.0 / (1.0 - c / 100.0).clamp_min(1.0 / 255.0))
        return ((x - 0.5) * k + 0.5).clamp(0.0, 1.0)
    b, c = b / 150.0, c / 100.0
    cx = torch.tensor(_CONTRAST_X, dtype=t.dtype, device=t.device)
    inner = cx[1:3] + torch.stack([-_CONTRAST_DELTA * torch.as_tensor(c), _CONTRAST_DELTA * torch.as_tensor(c)]).to(t)
    cy = torch.cat([cx[:1], inner, cx[3:]])
    contrast = natural_spline(cx, cy, t)
    bs = _brightness_spline(b, t)
    # A parametric curve: the brightness spline rotated 45°, added to the contrast curve, read back at t.
    return _interp(t, t - bs, contrast + bs).clamp(0.0, 1.0)


def brightness_contrast_lut(t: Tensor, p: Params) -> Tensor:
    """Brightness/contrast's table (psd-tools' ``apply_brightnesscontrast``; ``legacy``: the pre-CS3 linear one)."""
    return _brightness_contrast_curve(t, p).unsqueeze(0)


def exposure_lut(t: Tensor, p: Params) -> Tensor:
    """Exposure's table (psd-tools' ``apply_exposure``): x^2.2 · 2^exposure + offset, clamped, ^(1/γ), ^(1/2.2)."""
    e, off, g = _number(p["exposure"]), _number(p["offset"]), _number(p["gamma"])
    scale = 2.0**e if not isinstance(e, Tensor) else torch.exp2(e)
    x = (t**_EXPOSURE_GAMMA * scale + off).clamp(0.0, 1.0)
    x = torch.where(x > 0, x.clamp_min(ADJUST_POW_EPS) ** (1.0 / (g * _EXPOSURE_GAMMA)), torch.zeros_like(x))
    return x.unsqueeze(0)


# The tone-curve adjustments, as their tables: f(C) = apply_lut(C, table(ramp, p)).
TABLES: dict[str, Callable[[Tensor, Params], Tensor]] = {
    "levels": levels_lut,
    "curves": curves_lut,
    "brightness-contrast": brightness_contrast_lut,
    "exposure": exposure_lut,
}


def _tabled(name: str) -> Callable[[Tensor, Params], Tensor]:
    def f(C: Tensor, p: Params) -> Tensor:
        return apply_lut(C, TABLES[name](_ramp(C), p))

    f.__name__ = name.replace("-", "_")
    f.__doc__ = f"{name}: ``C`` through {TABLES[name].__name__}'s table."
    return f


levels, curves = _tabled("levels"), _tabled("curves")
brightness_contrast, exposure = _tabled("brightness-contrast"), _tabled("exposure")


def invert(C: Tensor, p: Params) -> Tensor:
    """Invert: 1 − C."""
    return 1.0 - C


def posterize(C: Tensor, p: Params) -> Tensor:
    """Posterize (psd-tools' ``apply_posterize``): floor(C·n·(2^b − 1)/2^b)/(n − 1), Photoshop's bins of b-bit codes."""
    n, codes = int(p["levels"]), 2.0 ** int(p.get("bits", 8))
    return torch.floor(C.clamp(0.0, 1.0) * (n * (codes - 1.0) / codes)) / (n - 1)


def luminosity(C: Tensor) -> Tensor:
    """0.3R + 0.59G + 0.11B (W3C Compositing Level 1's Lum, what Photoshop's threshold reads)."""
    return 0.3 * C[..., 0:1, :, :] + 0.59 * C[..., 1:2, :, :] + 0.11 * C[..., 2:3, :, :]


def threshold(C: Tensor, p: Params) -> Tensor:
    """Threshold: 1 where Lum(C) ≥ level, else 0, on every channel (Photoshop's level L of 255 compares codes:
    its level here is L/255 less half a code of the document's depth)."""
    white = (luminosity(C) >= _number(p["level"])).to(C.dtype)
    return white.expand_as(C) if C.shape[-3] == 3 else white


def rgb_to_hsl(C: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """H in [0, 1), S, L of the standard HSL double cone (psd-tools' ``rgb2hsl``)."""
    r, g, b = C[..., 0:1, :, :], C[..., 1:2, :, :], C[..., 2:3, :, :]
    mx, mn = C.amax(dim=-3, keepdim=True), C.amin(dim=-3, keepdim=True)
    d = mx - mn
    L = 0.5 * (mx + mn)
    grey = d <= ADJUST_POW_EPS
    dd = torch.where(grey, torch.ones_like(d), d)
    S = torch.where(grey, torch.zeros_like(d), d / (1.0 - (2.0 * L - 1.0).abs()).clamp_min(ADJUST_POW_EPS))
    h = torch.where(
        mx == r, torch.remainder((g - b) / dd, 6.0), torch.where(mx == g, (b - r) / dd + 2.0, (r - g) / dd + 4.0)
    )
    H = torch.where(grey, torch.zeros_like(d), h / 6.0)
    return H, S, L


def hsl_to_rgb(H: Tensor, S: Tensor, L: Tensor) -> Tensor:
    """The inverse of ``rgb_to_hsl``: f(n) = L − a·clamp(min(k − 3, 9 − k), −1, 1), k = (n + 12H) mod 12."""
    a = S * torch.minimum(L, 1.0 - L)
    out = []
    for n in (0.0, 8.0, 4.0):
        k = torch.remainder(n + 12.0 * H, 12.0)
        out.append(L - a * torch.minimum(k - 3.0, 9.0 - k).clamp(-1.0, 1.0))
    return torch.cat(out, dim=-3)


def _lighten(x: Tensor, lightness: Tensor | float) -> Tensor:
    """psd-tools' ``_apply_lightness``: towards white by l > 0, towards black by l < 0 (l in [−1, 1])."""
    if not isinstance(lightness, Tensor) and lightness == 0:
        return x
    pos = x * (1.0 - lightness) + lightness
    neg = x * (1.0 + lightness)
    up = lightness > 0 if isinstance(lightness, Tensor) else torch.tensor(lightness > 0)
    return torch.where(up.to(x.device), pos, neg).clamp(0.0, 1.0)


def hue_saturation(C: Tensor, p: Params) -> Tensor:
    """Hue/saturation (psd-tools' ``_huesaturation`` with the master channel; ``colorize``: its colorize)."""
    col = p.get("colorize")
    if col is not None:
        _, _, L = rgb_to_hsl(C)
        hue = torch.as_tensor(_number(col["hue"]) / 360.0, dtype=C.dtype, device=C.device) % 1.0
        sat = torch.as_tensor(_number(col["saturation"]) / 100.0, dtype=C.dtype, device=C.device)
        L = _lighten(L, _number(col["lightness"]) / 100.0)
        return hsl_to_rgb(hue.expand_as(L), sat.expand_as(L), L).clamp(0.0, 1.0)
    hue, s, lightness = _number(p["hue"]) / 360.0, _number(p["saturation"]) / 100.0, _number(p["lightness"]) / 100.0
    C = _lighten(C, lightness)
    H, S, L = rgb_to_hsl(C)
    ranges = [r for r in p.get("ranges") or () if any(_nonzero(r[k]) for k in ("hue", "saturation", "lightness"))]
    if not ranges:
        return hsl_to_rgb(torch.remainder(H + hue, 1.0), _saturate(S, s), L).clamp(0.0, 1.0)
    r_hue, r_sat, r_light = _range_shifts(H, ranges)
    # A range's lightness acts in HSV (psd-tools' _huesaturation): V darkened by l·S_V for l < 0, S_V reduced for
    # l > 0 (towards white), then back to HSL for the hue and saturation.
    V = L + S * torch.minimum(L, 1.0 - L)
    Sv = torch.where(V > ADJUST_POW_EPS, 2.0 * (1.0 - L / V.clamp_min(ADJUST_POW_EPS)), torch.zeros_like(V))
    V = torch.where(r_light >= 0, V, V * (1.0 + r_light * Sv)).clamp(0.0, 1.0)
    inv = 1.0 / (Sv + _RANGE_SAT_EPS)
    Sv = torch.where(
        r_light >= 0, Sv * (1.0 - r_light), 1.0 + (inv - 1.0) / (r_light.abs() - inv + _RANGE_SAT_EPS)
    ).clamp(0.0, 1.0)
    L = V * (1.0 - 0.5 * Sv)
    den = torch.minimum(L, 1.0 - L)
    S = torch.where(den > ADJUST_POW_EPS, (V - L) / den.clamp_min(ADJUST_POW_EPS), torch.zeros_like(L))
    H = torch.remainder(H + r_hue + hue, 1.0)
    return hsl_to_rgb(H, _saturate(_saturate(S, s), r_sat), L).clamp(0.0, 1.0)


# psd-tools' _correct_saturation's guard against 1/0 (an unsaturated pixel under a darkening range).
_RANGE_SAT_EPS = 1e-3


def _nonzero(x: Any) -> bool:
    return isinstance(x, Tensor) or x != 0


def _range_mask(H: Tensor, corners: Any) -> Tensor:
    """psd-tools' ``_get_huesaturation_range_mask``: the trapezoid [begin, full_begin, full_end, end] (degrees,
    read on the circle from ``begin``) at hue ``H`` in [0, 1): 0 outside, rising, 1, falling."""
    bl, tl, tr, br = (_number(c) / 360.0 for c in corners)
    x = torch.remainder(H - bl, 1.0)
    left, center, right = (tl - bl) % 1.0, (tr - bl) % 1.0, (br - bl) % 1.0
    rise = x / max(left, ADJUST_POW_EPS) if not isinstance(left, Tensor) else x / left.clamp_min(ADJUST_POW_EPS)
    fall_den = right - center
    fall = (right - x) / (fall_den if isinstance(fall_den, Tensor) else max(fall_den, ADJUST_POW_EPS))
    one = torch.ones_like(x)
    zero = torch.zeros_like(x)
    return torch.where(
        (x >= left) & (x <= center), one, torch.where(x < left, rise, torch.where(x <= right, fall, zero))
    ).clamp(0.0, 1.0)


def _range_shifts(H: Tensor, ranges: list) -> tuple[Tensor, Tensor, Tensor]:
    """Per pixel, the colour ranges' hue, saturation and lightness shifts (in order; psd-tools'
    ``_get_colorrange_hsl_values``): each scaled by the range's mask, a positive saturation by
    1 − (1 − mask)^(1.5/(1 − s⁴ + 0.05)). Where two ranges that change saturation overlap, psd-tools combines them
    through an empirical 21×21 grid fitted to Photoshop; here they add (clamped to [−1, 1]), which is exact where at
    most one of them is non-zero (the grid's f(0, y) = y)."""
    zero = torch.zeros_like(H)
    r_hue, r_sat, r_light = zero, zero, zero
    for r in ranges:
        m = _range_mask(H, r["range"])
        h, sat, light = _number(r["hue"]) / 360.0, _number(r["saturation"]) / 100.0, _number(r["lightness"]) / 100.0
        r_hue = r_hue + h * m
        r_light = (r_light + light * m).clamp(-1.0, 1.0)
        if _nonzero(sat):
            pos = sat * (1.0 - (1.0 - m) ** (1.5 / (1.0 - sat**4 + 0.05)))
            up = sat > 0 if isinstance(sat, Tensor) else torch.tensor(sat > 0)
            r_sat = (r_sat + torch.where(up.to(H.device), pos, sat * m)).clamp(-1.0, 1.0)
    return r_hue, r_sat, r_light


def _saturate(S: Tensor, s: Tensor | float) -> Tensor:
    """psd-tools' ``_apply_saturation``: S/(1 − s + slack) for s > 0, S·(1 + s) for s ≤ 0 (s in [−1, 1])."""
    if not isinstance(s, Tensor) and s == 0:
        return S
    more = S / (1.0 - s + _SATURATION_SLACK)
    less = S * (1.0 + s)
    up = s > 0 if isinstance(s, Tensor) else torch.tensor(s > 0)
    return torch.where(up.to(S.device), more, less).clamp(0.0, 1.0)


def _vector(values: Any, like: Tensor, scale: float = 1.0) -> Tensor:
    """A parameter list (numbers or tensors, or one tensor) as a float tensor of ``like``'s dtype, times ``scale``."""
    if isinstance(values, Tensor):
        return values.to(like.dtype) * scale
    parts = [v.to(like.dtype) if isinstance(v, Tensor) else torch.tensor(float(v), dtype=like.dtype) for v in values]
    return torch.stack(parts).to(like.device) * scale


def _per_channel(v: Tensor) -> Tensor:
    """A (3,) vector shaped to broadcast over ``(..., 3, h, w)``."""
    return v.view(3, 1, 1)


def channel_mixer(C: Tensor, p: Params) -> Tensor:
    """Channel mixer (Photoshop's dialog, Adobe's "Mix color channels"): output channel c is Σ_k w_ck/100 · C_k +
    constant_c/100, clamped; with ``gray`` ("Monochrome") the one row is every channel's. Linear: exact."""
    rows = [p["gray"]] * 3 if p.get("gray") is not None else [p["red"], p["green"], p["blue"]]
    M = torch.stack([_vector(r, C, 0.01) for r in rows])  # (3, 4): weights of R, G, B and the constant
    out = torch.einsum("ck,...khw->...chw", M[:, :3], C) + _per_channel(M[:, 3])
    return out.clamp(0.0, 1.0)


# GIMP's colour balance masks (app/operations/gimpoperationcolorbalance.c): ramps of width a at lightness b and 1 − b,
# each range's shift scaled by 0.7; the three masks sum to 0.7 everywhere.
_BALANCE_A, _BALANCE_B, _BALANCE_SCALE = 0.25, 0.333, 0.7


def color_balance(C: Tensor, p: Params) -> Tensor:
    """Color balance as GIMP 2.10 computes it (``gimp_operation_color_balance_map``; Photoshop's formula is not
    published, GIMP's and Krita's dialogs mirror its controls): C + Σ_range shift/100 · mask_range(L), clamped, L the
    HSL lightness; ``preserve_luminosity`` puts the result's HSL hue and saturation at the input's lightness."""
    L = 0.5 * (C.amax(dim=-3, keepdim=True) + C.amin(dim=-3, keepdim=True))
    a, b, k = _BALANCE_A, _BALANCE_B, _BALANCE_SCALE
    shadows = ((L - b) / -a + 0.5).clamp(0.0, 1.0) * k
    midtones = ((L - b) / a + 0.5).clamp(0.0, 1.0) * ((L + b - 1.0) / -a + 0.5).clamp(0.0, 1.0) * k
    highlights = ((L + b - 1.0) / a + 0.5).clamp(0.0, 1.0) * k
    out = C
    for name, w in (("shadows", shadows), ("midtones", midtones), ("highlights", highlights)):
        out = out + _per_channel(_vector(p[name], C, 0.01)) * w
    out = out.clamp(0.0, 1.0)
    if p.get("preserve_luminosity", True):
        H, S, _ = rgb_to_hsl(out)
        out = hsl_to_rgb(H, S, L).clamp(0.0, 1.0)
    return out


def vibrance(C: Tensor, p: Params) -> Tensor:
    """Vibrance: in HSL, ``saturation`` as hue/saturation's (``_saturate``), then S + v·S·(1 − S), v = vibrance/100:
    the mid-saturated colours move most, gray and full colours stay. Photoshop's formula is not published; this is
    the saturation-weighted gain that vibrance names (it does not model Photoshop's protection of skin tones)."""
    v, s = _number(p["vibrance"]) / 100.0, _number(p["saturation"]) / 100.0
    H, S, L = rgb_to_hsl(C)
    S = _saturate(S, s)
    S = (S + v * S * (1.0 - S)).clamp(0.0, 1.0)
    return hsl_to_rgb(H, S, L).clamp(0.0, 1.0)


def black_and_white(C: Tensor, p: Params) -> Tensor:
    """Black & white (Photoshop's six-slider conversion, as Photopea and the PSD format's six weights describe it):
    with a pixel's channels sorted max ≥ mid ≥ min, gray = min + (max − mid)·w_primary + (mid − min)·w_secondary,
    the primary the max channel's (reds, greens, blues) and the secondary the pair max+mid's (yellows = R+G, cyans
    = G+B, magentas = R+B); with the defaults a pure red is 40 % gray, a yellow 60 %. ``tint``: the gray takes the
    tint's hue and saturation at its luminosity (W3C SetLum, the color blend mode)."""
    srt, idx = torch.sort(C, dim=-3, descending=True)
    mx, mid, mn = srt[..., 0:1, :, :], srt[..., 1:2, :, :], srt[..., 2:3, :, :]
    primary = _vector([p["reds"], p["greens"], p["blues"]], C, 0.01)
    secondary = _vector([p["cyans"], p["magentas"], p["yellows"]], C, 0.01)  # indexed by the min channel
    gray = mn + (mx - mid) * primary[idx[..., 0:1, :, :]] + (mid - mn) * secondary[idx[..., 2:3, :, :]]
    gray = gray.clamp(0.0, 1.0)
    if p.get("tint") is None:
        return gray.expand_as(C)
    tint = _per_channel(_vector(p["tint"], C)).expand_as(C)
    return _set_lum(tint, gray).clamp(0.0, 1.0)


def gradient_map_lut(t: Tensor, p: Params) -> Tensor:
    """Gradient map's (3, N) table over luminosity: the colour stops read at ``t`` with their midpoints
    (``gradient.interpolate_stops``, the one reading of a gradient's stops); ``reverse`` reads it from 1 down."""
    stops = p["stops"]
    xs = _vector([s["location"] for s in stops], t)
    cs = torch.stack([_vector(s["color"], t) for s in stops], dim=1)  # (3, n)
    ms = _vector([s.get("midpoint", 0.5) for s in stops], t)
    if p.get("reverse"):
        t = 1.0 - t
    return interpolate_stops(t, xs, cs, ms)


def gradient_map(C: Tensor, p: Params) -> Tensor:
    """Gradient map: Lum(C) (0.3R + 0.59G + 0.11B) through ``gradient_map_lut``'s table."""
    return apply_lut(luminosity(C).expand_as(C), gradient_map_lut(_ramp(C), p))


def photo_filter(C: Tensor, p: Params) -> Tensor:
    """Photo filter: the colour multiplied by the filter's at ``density`` (C + d·(C·F − C), Photoshop's "simulates a
    colored filter in front of the lens"; its exact formula is not published), then, with ``preserve_luminosity``,
    moved back to the input's luminosity (W3C SetLum with ClipColor)."""
    F = _per_channel(_vector(p["color"], C))
    d = _number(p["density"]) / 100.0
    out = C + d * (C * F - C)
    if p.get("preserve_luminosity", True):
        out = _set_lum(out, luminosity(C))
    return out.clamp(0.0, 1.0)


ADJUSTMENTS: dict[str, Callable[[Tensor, Params], Tensor]] = {
    "levels": levels,
    "curves": curves,
    "hue-saturation": hue_saturation,
    "brightness-contrast": brightness_contrast,
    "exposure": exposure,
    "invert": invert,
    "posterize": posterize,
    "threshold": threshold,
    "channel-mixer": channel_mixer,
    "color-balance": color_balance,
    "vibrance": vibrance,
    "black-and-white": black_and_white,
    "gradient-map": gradient_map,
    "photo-filter": photo_filter,
}


def _tensors(p: Any) -> list[Tensor]:
    if isinstance(p, Tensor):
        return [p]
    if isinstance(p, Mapping):
        return [t for v in p.values() for t in _tensors(v)]
    if isinstance(p, (list, tuple)):
        return [t for v in p for t in _tensors(v)]
    return []


def _finite(p: Any, where: str) -> None:
    if isinstance(p, Mapping):
        for k, v in p.items():
            _finite(v, f"{where}.{k}")
    elif isinstance(p, (list, tuple)):
        if len(p) > 4 * MAX_CURVE_POINTS:
            raise LasagnaError(f"holds {len(p)} values; expected at most {MAX_CURVE_POINTS} curve points", where=where)
        for i, v in enumerate(p):
            _finite(v, f"{where}[{i}]")
    elif isinstance(p, Tensor):
        if not p.is_floating_point() or not bool(torch.isfinite(p.detach()).all()):
            raise LasagnaError(f"is a tensor {p.dtype} with non-finite values; expected finite floats", where=where)
    elif isinstance(p, float) and not math.isfinite(p):
        raise LasagnaError(f"is {p}; expected a finite number", where=where)


@dataclass(frozen=True, eq=False)
class Adjustment:
    """An adjustment of ``type`` (a key of ``ADJUSTMENTS``) with its parameters; calling it adjusts a colour."""

    type: str
    params: Params = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.type not in ADJUSTMENTS:
            raise LasagnaError(
                f"unknown adjustment {self.type!r}; expected one of {', '.join(ADJUSTMENTS)}", where="adjustment.type"
            )
        _finite(self.params, "adjustment")

    @property
    def requires_grad(self) -> bool:
        return any(t.requires_grad for t in _tensors(self.params))

    def tensors(self) -> list[Tensor]:
        """Every parameter tensor (for gradients and fingerprints)."""
        return _tensors(self.params)

    def fingerprint(self) -> tuple[Any, ...]:
        """What a render's result depends on: the type and the parameters (tensors by identity and version)."""

        def fp(p: Any) -> Any:
            if isinstance(p, Tensor):
                return ("tensor", id(p), p._version)
            if isinstance(p, Mapping):
                return tuple((k, fp(v)) for k, v in sorted(p.items()))
            if isinstance(p, (list, tuple)):
                return tuple(fp(v) for v in p)
            return p

        return (self.type, fp(self.params))

    def table(self, dtype: torch.dtype, device: torch.device) -> Tensor:
        """A tone-curve adjustment's table in ``dtype`` on ``device``, built once while no parameter needs grad."""
        key = (dtype, device)
        if self.requires_grad:
            return TABLES[self.type](torch.linspace(0.0, 1.0, LUT_SIZE, dtype=dtype, device=device), self.params)
        cache = self.__dict__.setdefault("_tables", {})
        if key not in cache:
            with torch.no_grad():
                cache[key] = TABLES[self.type](
                    torch.linspace(0.0, 1.0, LUT_SIZE, dtype=dtype, device=device), self.params
                )
        return cache[key]

    def __call__(self, C: Tensor) -> Tensor:
        """The adjusted colour of ``C (..., 3, h, w)`` (a gray ``(..., 1, h, w)`` is broadcast to RGB first)."""
        if C.shape[-3] == 1:
            C = C.expand(*C.shape[:-3], 3, *C.shape[-2:])
        if self.type in TABLES:
            return apply_lut(C, self.table(C.dtype, C.device))
        return ADJUSTMENTS[self.type](C, self.params)


__all__ = ["ADJUSTMENTS", "Adjustment", "LUT_SIZE", "apply_lut", "natural_spline", "rgb_to_hsl", "hsl_to_rgb"]
