"""sRGB transfer functions: IEC 61966-2-1 decode (sRGB → linear light) and encode (linear → sRGB); Rec. 709 luma.

Used when a document asks for ``blend_space="linear"``: colour values are decoded, blended in linear
light, and the composite is encoded back. Multiply factors are ratios of linear light and are never
passed through these functions (docs/ARCHITECTURE.md).

Both functions use the exact constants of IEC 61966-2-1:1999 (the piecewise curve with the linear
toe: threshold 0.04045 / 0.0031308, slope 12.92, offset 0.055, exponent 2.4), and extend the curve
to negative values odd-symmetrically, ``f(x) = sign(x)·f(|x|)``, as CSS Color Module Level 4 does
for its "extended" sRGB (values outside [0, 1] appear in unclamped intermediates). Values above 1
follow the power segment.

Autograd: each branch of the select (``lasagna.compose.select.pick``, a ``torch.where``) is evaluated
everywhere, and the gradient of the branch *not* selected still enters the backward pass multiplied by
zero — ``0·inf`` or ``0·nan`` would poison it. The power segment therefore reads its argument clamped to
the power domain (``|x| ≥ threshold``), so its gradient is finite at 0 where the linear segment is
selected (gradient 1/12.92 at x = 0 for decode, 12.92 for encode). All arithmetic stays in the input's
dtype (float64-safe: the constants are Python floats, exact to the printed digits in float64).

The standard's two segments do not meet exactly (0.04045 / 12.92 = 0.0031308049…): decode jumps by
2.3e-9 at its threshold and encode by 2.9e-8 at its own, so a float64 round trip is exact to 3e-8 for
values between the two thresholds and to ~1e-15 elsewhere (tested).

**Luma** (``luma``, ``set_luma``): Rec. ITU-R BT.709 luma Y = 0.2126 R + 0.7152 G + 0.0722 B of stored
(sRGB-encoded) values, as image editors take it — the gray image the colourisation prior is conditioned on
and the world's colorize task starts from. ``set_luma(C, Y)`` is W3C Compositing Level 1's SetLum (section
10.3: C + (Y − Lum(C)), then ClipColor, which pulls an out-of-gamut colour toward its luma along the line of
constant luma) with the Rec. 709 weights instead of the spec's 0.3/0.59/0.11: the result lies in [0, 1] and
its luma is Y exactly (for Y in [0, 1]; up to float rounding) — a colour over a luminance.
"""

from __future__ import annotations

import torch

from lasagna.compose.select import pick, step
from lasagna.errors import LasagnaError
from lasagna.numerics import CLIP_COLOR_EPS

# IEC 61966-2-1:1999, section 5.2 (encoding) and 5.3 (decoding).
SRGB_DECODE_THRESHOLD = 0.04045  # encoded value where the linear toe ends
SRGB_ENCODE_THRESHOLD = 0.0031308  # linear value where the linear toe ends
SRGB_SLOPE = 12.92
SRGB_OFFSET = 0.055
SRGB_GAMMA = 2.4

REC709 = (0.2126, 0.7152, 0.0722)
"""Rec. ITU-R BT.709 luma weights, applied to stored (sRGB-encoded) values as image editors do."""


def _check(x: torch.Tensor, where: str) -> None:
    if not isinstance(x, torch.Tensor) or not x.is_floating_point():
        got = x.dtype if isinstance(x, torch.Tensor) else type(x).__name__
        raise LasagnaError(f"expected a floating-point tensor, got {got}", where=where)


def srgb_to_linear(x: torch.Tensor) -> torch.Tensor:
    """Decode sRGB-encoded values to linear light (IEC 61966-2-1, extended odd-symmetrically).

    ``x/12.92`` for ``|x| ≤ 0.04045``, else ``sign(x)·((|x| + 0.055)/1.055)^2.4``. Differentiable,
    with a finite gradient everywhere (1/12.92 at 0).
    """
    _check(x, "srgb_to_linear")
    a = x.abs()
    # Clamp into the power segment's domain so its (unselected) gradient stays finite near 0.
    power = ((a.clamp_min(SRGB_DECODE_THRESHOLD) + SRGB_OFFSET) / (1.0 + SRGB_OFFSET)).pow(SRGB_GAMMA)
    return pick(step("<=", a, SRGB_DECODE_THRESHOLD), x / SRGB_SLOPE, torch.copysign(power, x))


def linear_to_srgb(y: torch.Tensor) -> torch.Tensor:
    """Encode linear-light values to sRGB (IEC 61966-2-1, extended odd-symmetrically).

    ``12.92·y`` for ``|y| ≤ 0.0031308``, else ``sign(y)·(1.055·|y|^(1/2.4) − 0.055)``.
    Differentiable, with a finite gradient everywhere (12.92 at 0; ``|y|^(1/2.4)`` has an infinite
    slope at 0, which is why its argument is clamped to the power segment's domain).
    """
    _check(y, "linear_to_srgb")
    a = y.abs()
    power = (1.0 + SRGB_OFFSET) * a.clamp_min(SRGB_ENCODE_THRESHOLD).pow(1.0 / SRGB_GAMMA) - SRGB_OFFSET
    return pick(step("<=", a, SRGB_ENCODE_THRESHOLD), y * SRGB_SLOPE, torch.copysign(power, y))


def srgb_to_linear_derivative(x: torch.Tensor) -> torch.Tensor:
    """d srgb_to_linear / dx: 1/12.92 on the toe, else (2.4/1.055)·((|x| + 0.055)/1.055)^1.4 (even in x)."""
    _check(x, "srgb_to_linear_derivative")
    a = x.abs()
    power = (SRGB_GAMMA / (1.0 + SRGB_OFFSET)) * (
        (a.clamp_min(SRGB_DECODE_THRESHOLD) + SRGB_OFFSET) / (1.0 + SRGB_OFFSET)
    ).pow(SRGB_GAMMA - 1.0)
    return pick(step("<=", a, SRGB_DECODE_THRESHOLD), torch.full_like(x, 1.0 / SRGB_SLOPE), power)


def linear_to_srgb_derivative(y: torch.Tensor) -> torch.Tensor:
    """d linear_to_srgb / dy: 12.92 on the toe, else (1.055/2.4)·|y|^(1/2.4 − 1) (even in y)."""
    _check(y, "linear_to_srgb_derivative")
    a = y.abs()
    power = ((1.0 + SRGB_OFFSET) / SRGB_GAMMA) * a.clamp_min(SRGB_ENCODE_THRESHOLD).pow(1.0 / SRGB_GAMMA - 1.0)
    return pick(step("<=", a, SRGB_ENCODE_THRESHOLD), torch.full_like(y, SRGB_SLOPE), power)


def luma(image: torch.Tensor) -> torch.Tensor:
    """Rec. 709 luma (..., 1, H, W) of RGB values (..., 3, H, W) (module docstring)."""
    r, g, b = REC709
    return r * image[..., 0:1, :, :] + g * image[..., 1:2, :, :] + b * image[..., 2:3, :, :]


def set_luma(color: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """W3C SetLum with Rec. 709 weights (module docstring): ``color`` (..., 3, H, W) moved to luma ``y``
    (..., 1, H, W) and clipped into [0, 1] along constant luma (ClipColor). Differentiable; the guarded
    denominators are ``numerics.CLIP_COLOR_EPS`` (a gray needs no clipping: its quotient is never selected)."""
    _check(color, "set_luma")
    c = color + (y - luma(color))
    lum = luma(c)
    n = c.amin(dim=-3, keepdim=True)
    x = c.amax(dim=-3, keepdim=True)  # the spec takes x before the first correction
    c = pick(step("<", n, 0.0), lum + (c - lum) * lum / (lum - n).clamp_min(CLIP_COLOR_EPS), c)
    return pick(step(">", x, 1.0), lum + (c - lum) * (1.0 - lum) / (x - lum).clamp_min(CLIP_COLOR_EPS), c)
