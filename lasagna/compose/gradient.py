"""Gradient fills: Photoshop's five ramp styles over an anchor box, read through colour and opacity stops.

The ramp is psd-tools' ``draw_gradient_fill`` (``psd_tools/composite/paint.py``), which models Photoshop's gradient
fill layers. With the anchor box (x0, y0, x1, y1) — the layer's rectangle, or the canvas — of sides W = max(x1 − x0,
1) and H = max(y1 − y0, 1), the angle a in degrees (θ in radians) and the scale in percent:

1. s = scale/100 · ((90 − r)/90 · W + r/90 · H), r = a mod 90 (the ramp's length follows the side it runs along);
2. a pixel (i, j) of the canvas (its top-left corner) has u = 2(i − x0)/(W − 1) − 1 (−1 when W = 1), v likewise
   over H, each minus twice its ``shift`` fraction (Photoshop's offset, in percent of the box; psd-tools ignores it);
   X = u·W/s, Y = v·H/s (Y grows downwards);
3. z by style: linear ½(X cos θ − Y sin θ + 1); radial √(X² + Y²); angle ((atan2(Y, X)·180/π + a) mod 360)/360;
   reflected |X cos θ − Y sin θ|; diamond |X cos θ − Y sin θ| + |X sin θ + Y cos θ|;
4. t = clamp(z, 0, 1), and 1 − t with ``reverse``.

The colour at t interpolates the colour stops (``interpolate_stops``: between stops i and i+1 the fraction of the
way is bent so that stop i's midpoint gives ½; psd-tools interpolates linearly, which is a midpoint of ½), the alpha
the opacity stops the same way (none: opaque). No dither (Photoshop's adds at most one code of noise). The ramp is
built in float64 and cast once; the colours are differentiable in the stops' colours, opacities and midpoints.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from lasagna.errors import LasagnaError
from lasagna.limits import MAX_GRADIENT_STOPS
from lasagna.numerics import ADJUST_POW_EPS

Box = tuple[int, int, int, int]  # (x0, y0, x1, y1) in canvas pixels
STYLES = ("linear", "radial", "angle", "reflected", "diamond")


def _values(values: Sequence[Any] | Tensor, dtype: torch.dtype, device: torch.device | None) -> Tensor:
    """Numbers or tensors (or one tensor) as one tensor of ``dtype``; tensors keep their graph."""
    if isinstance(values, Tensor):
        return values.to(dtype=dtype, device=device)
    parts = [
        v.to(dtype=dtype, device=device) if isinstance(v, Tensor) else torch.tensor(v, dtype=dtype, device=device)
        for v in values
    ]
    return torch.stack(parts)


def interpolate_stops(t: Tensor, xs: Tensor, values: Tensor, midpoints: Tensor) -> Tensor:
    """Stops' ``values (C, n)`` at locations ``xs (n,)`` (increasing) read at ``t (...)`` → ``(C, ...)``: between
    stops i and i+1 the fraction u of the way is bent so that the midpoint m of stop i gives ½ — 0.5·u/m below it,
    0.5 + 0.5·(u − m)/(1 − m) above (GIMP's linear segment, ``gimp_gradient_calc_linear_factor``; Photoshop's stop
    midpoints mean the same) — and the values are mixed by it; the end values beyond the end stops. Two stops at
    one location are a hard edge (the later one wins from there on, as psd-tools keeps the last)."""
    tc = t.clamp(xs[0], xs[-1])
    k = torch.searchsorted(xs[1:-1].detach().contiguous(), tc.detach().contiguous(), right=True)
    x0, x1, m = xs[k], xs[k + 1], midpoints[k]
    u = ((tc - x0) / (x1 - x0).clamp_min(ADJUST_POW_EPS)).clamp(0.0, 1.0)
    f = torch.where(u <= m, 0.5 * u / m, 0.5 + 0.5 * (u - m) / (1.0 - m))
    return values[:, k] + f * (values[:, k + 1] - values[:, k])


def _axis(start: int, count: int, extent: int, shift: float) -> Tensor:
    """``count`` normalised coordinates u from canvas pixel ``start`` of a box side of ``extent`` pixels (its first
    pixel −1, its last +1), moved by ``shift`` percent of the side, in float64."""
    step = 2.0 / (extent - 1) if extent > 1 else 0.0
    return -1.0 + torch.arange(start, start + count, dtype=torch.float64) * step - 2.0 * shift / 100.0


def ramp(style: str, angle: float, scale: float, shift: Sequence[float], box: Box, viewport: Box) -> Tensor:
    """The ramp position t ∈ [0, 1] (before ``reverse``) of every pixel of ``viewport`` (h, w), float64, laid out
    on the anchor ``box`` (module docstring, steps 1–4)."""
    if style not in STYLES:
        raise LasagnaError(f"unknown gradient style {style!r}; expected one of {', '.join(STYLES)}", "gradient.style")
    for name, v in (("angle", angle), ("scale", scale), ("shift", shift[0]), ("shift", shift[1])):
        if not math.isfinite(float(v)):
            raise LasagnaError(f"is {v}; expected a finite number", f"gradient.{name}")
    if not float(scale) > 0.0:
        raise LasagnaError(f"is {scale}; expected a scale above 0 percent", "gradient.scale")
    bw, bh = max(box[2] - box[0], 1), max(box[3] - box[1], 1)
    r = float(angle) % 90.0
    s = float(scale) / 100.0 * ((90.0 - r) / 90.0 * bw + r / 90.0 * bh)
    w, h = viewport[2] - viewport[0], viewport[3] - viewport[1]
    X = (_axis(viewport[0] - box[0], w, bw, float(shift[0])) * (bw / s)).view(1, w)
    Y = (_axis(viewport[1] - box[1], h, bh, float(shift[1])) * (bh / s)).view(h, 1)
    theta = math.radians(float(angle) % 360.0)
    c, sn = math.cos(theta), math.sin(theta)
    if style == "linear":
        z = 0.5 * (c * X - sn * Y + 1.0)
    elif style == "radial":
        z = torch.sqrt(X * X + Y * Y)
    elif style == "angle":
        z = torch.remainder(torch.rad2deg(torch.atan2(Y.expand(h, w), X.expand(h, w))) + float(angle), 360.0) / 360.0
    elif style == "reflected":
        z = (c * X - sn * Y).abs()
    else:  # diamond
        z = (c * X - sn * Y).abs() + (sn * X + c * Y).abs()
    return z.expand(h, w).clamp(0.0, 1.0)


def _stops(stops: Sequence[Mapping[str, Any]], key: str, dtype: torch.dtype, device) -> tuple[Tensor, Tensor, Tensor]:
    if not 2 <= len(stops) <= MAX_GRADIENT_STOPS:
        raise LasagnaError(f"holds {len(stops)} stops; expected 2 to {MAX_GRADIENT_STOPS}", f"gradient.{key}")
    xs = _values([s["location"] for s in stops], dtype, device)
    ms = _values([s.get("midpoint", 0.5) for s in stops], dtype, device)
    if key == "stops":
        vs = torch.stack([_values(s["color"], dtype, device) for s in stops], dim=1)  # (3, n)
    else:
        vs = _values([s["opacity"] for s in stops], dtype, device).view(1, -1)  # (1, n)
    for name, x in (("locations", xs), ("midpoints", ms), ("values", vs)):
        if not bool(torch.isfinite(x.detach()).all()):
            raise LasagnaError(f"{name} hold NaN or infinite values; expected finite numbers", f"gradient.{key}")
    if bool((xs.detach()[1:] < xs.detach()[:-1]).any()):
        raise LasagnaError("locations are not sorted; expected stops in increasing location", f"gradient.{key}")
    return xs, vs, ms


def gradient_fill(
    p: Mapping[str, Any], box: Box, viewport: Box, dtype: torch.dtype | None = None, device=None
) -> tuple[Tensor, Tensor | None]:
    """A gradient fill's colour ``(3, h, w)`` and alpha ``(1, h, w)`` (None: no opacity stops, opaque) on
    ``viewport``, its ramp laid out on ``box`` (both (x0, y0, x1, y1) in canvas pixels). ``p`` is the document's
    ``gradient`` as a plain dict; stop colours and opacities may be tensors (the result is differentiable in them)."""
    dtype = dtype or torch.get_default_dtype()
    t = ramp(
        p.get("style", "linear"), p.get("angle", 90.0), p.get("scale", 100.0), p.get("shift", (0.0, 0.0)), box, viewport
    )
    if p.get("reverse"):
        t = 1.0 - t
    t = t.to(dtype=dtype, device=device)
    xs, cs, ms = _stops(p["stops"], "stops", dtype, device)
    color = interpolate_stops(t, xs, cs, ms)
    alpha = None
    if p.get("opacity_stops") is not None:
        xa, va, ma = _stops(p["opacity_stops"], "opacity_stops", dtype, device)
        alpha = interpolate_stops(t, xa, va, ma)
    return color, alpha


__all__ = ["STYLES", "gradient_fill", "interpolate_stops", "ramp"]
