"""Relief on the wall: a height field h(x, y) that bends the wall's normals and not its albedo.

The wall stays the plane z = ``WALL_Z`` for visibility and depth (a bump map, not a displacement);
its normal becomes n = (−∂h/∂x, −∂h/∂y, 1)/‖·‖, so the true shading shows the relief while the
albedo — what a shading layer is conditioned on — does not. Relief is drawn independently of the
wall's paint: the world's evidence that shading detail and texture detail are different things.

A family is a closed-form gradient ``gradient(x, y, prm) -> (∂h/∂x, ∂h/∂y)`` on flat (N,) tensors
with per-point parameters ``prm`` (N, N_RELIEF_PARAMS), and a sampler mapping ``RELIEF_DRAWS``
uniforms to a parameter row. Slopes are drawn so that each bump, groove or rim tilts the normal by
17°–50° at its steepest (|∇h| ∈ [0.3, 1.2]; overlapping bumps or bevels add): visible at 32².

Families (``RELIEFS``; which split uses which is in ``lasagna.world.splits``):

=========  =====================================================================================
bumps      five Gaussian bumps and dents h = Σ Aᵢ·exp(−|p − cᵢ|²/2σᵢ²), signs drawn per bump
grooves    parallel grooves of period P along an angle: h = −D·sin²(πξ) on the groove (ξ ∈ [0, 1))
bevels     two raised rectangles with sloped rims: h = s·clamp(distance inside the edge, 0, width)
ripples    concentric waves about a centre, 2–4 whole wavelengths: h = A·sin(2πr/λ) for r < reach
=========  =====================================================================================
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

Tensor = torch.Tensor

N_RELIEF_PARAMS = 20
RELIEF_DRAWS = 20
_SLOPE = (0.3, 1.2)
_BUMPS = 5


def _lerp(u: float, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(u)


def _sign(u: float) -> float:
    return 1.0 if u < 0.5 else -1.0


def bumps(x: Tensor, y: Tensor, prm: Tensor) -> tuple[Tensor, Tensor]:
    gx, gy = torch.zeros_like(x), torch.zeros_like(x)
    for i in range(_BUMPS):
        cx, cy, sigma, amp = (prm[:, 4 * i + j] for j in range(4))
        dx, dy = x - cx, y - cy
        e = amp * torch.exp(-(dx * dx + dy * dy) / (2.0 * sigma * sigma)) / (sigma * sigma)
        gx, gy = gx - e * dx, gy - e * dy
    return gx, gy


def _sample_bumps(u: np.ndarray) -> np.ndarray:
    out = np.zeros(N_RELIEF_PARAMS)
    for i in range(_BUMPS):
        cx, cy, s, sl = u[4 * i : 4 * i + 4]
        sigma = _lerp(s, 0.06, 0.3)
        # The steepest slope of a Gaussian A·exp(−r²/2σ²) is A/(σ√e): solve for A.
        slope = _lerp(abs(2.0 * sl - 1.0), *_SLOPE)
        out[4 * i : 4 * i + 4] = (
            _lerp(cx, -1.0, 1.0),
            _lerp(cy, -1.0, 1.0),
            sigma,
            _sign(sl) * slope * sigma * math.sqrt(math.e),
        )
    return out


def grooves(x: Tensor, y: Tensor, prm: Tensor) -> tuple[Tensor, Tensor]:
    phi, period, width, depth, offset = (prm[:, j] for j in range(5))
    c, s = torch.cos(phi), torch.sin(phi)
    a = c * x + s * y + offset
    xi = torch.remainder(a, period) / (width * period)
    on = xi < 1.0
    dh_da = torch.where(on, -depth * math.pi * torch.sin(2.0 * math.pi * xi) / (width * period), torch.zeros_like(x))
    return dh_da * c, dh_da * s


def _sample_grooves(u: np.ndarray) -> np.ndarray:
    out = np.zeros(N_RELIEF_PARAMS)
    period, width = _lerp(u[1], 0.15, 0.5), _lerp(u[2], 0.2, 0.6)
    # The steepest slope of −D·sin²(πξ) over a groove of width w·P is D·π/(w·P).
    depth = _lerp(u[3], *_SLOPE) * width * period / math.pi
    out[:5] = (2.0 * math.pi * u[0], period, width, depth, 10.0 * u[4])
    return out


def bevels(x: Tensor, y: Tensor, prm: Tensor) -> tuple[Tensor, Tensor]:
    gx, gy = torch.zeros_like(x), torch.zeros_like(x)
    for i in range(2):
        cx, cy, hx, hy, rim, slope = (prm[:, 6 * i + j] for j in range(6))
        dx, dy = x - cx, y - cy
        ex, ey = hx - dx.abs(), hy - dy.abs()  # distance inside the rectangle from each pair of edges
        on_rim = (torch.minimum(ex, ey) > 0) & (torch.minimum(ex, ey) < rim)
        # h = slope·min(ex, ey) on the rim: its gradient is the nearer edge's inward direction.
        use_x = ex <= ey
        gx = gx + torch.where(on_rim & use_x, -slope * torch.sign(dx), torch.zeros_like(x))
        gy = gy + torch.where(on_rim & ~use_x, -slope * torch.sign(dy), torch.zeros_like(x))
    return gx, gy


def _sample_bevels(u: np.ndarray) -> np.ndarray:
    out = np.zeros(N_RELIEF_PARAMS)
    for i in range(2):
        v = u[6 * i : 6 * i + 6]
        hx, hy = _lerp(v[2], 0.15, 0.6), _lerp(v[3], 0.15, 0.6)
        out[6 * i : 6 * i + 6] = (
            _lerp(v[0], -0.8, 0.8),
            _lerp(v[1], -0.8, 0.8),
            hx,
            hy,
            _lerp(v[4], 0.04, 0.4) * min(hx, hy),
            _lerp(v[5], *_SLOPE),
        )
    return out


def ripples(x: Tensor, y: Tensor, prm: Tensor) -> tuple[Tensor, Tensor]:
    cx, cy, wavelength, amp, reach = (prm[:, j] for j in range(5))
    dx, dy = x - cx, y - cy
    r = torch.sqrt(dx * dx + dy * dy).clamp_min(1e-12)
    k = 2.0 * math.pi / wavelength
    # h = A·sin(k·r) inside r < reach (whole waves, so h is 0 at the edge): ∂h/∂r = A·k·cos(k·r).
    dh_dr = torch.where(r < reach, amp * k * torch.cos(k * r), torch.zeros_like(x))
    return dh_dr * dx / r, dh_dr * dy / r


def _sample_ripples(u: np.ndarray) -> np.ndarray:
    out = np.zeros(N_RELIEF_PARAMS)
    wavelength = _lerp(u[2], 0.15, 0.4)
    # The steepest slope of A·sin(k·r) is A·k: solve for A.
    amp = _lerp(u[3], *_SLOPE) * wavelength / (2.0 * math.pi)
    reach = wavelength * (2 + int(u[4] * 3))  # 2–4 whole waves
    out[:5] = (_lerp(u[0], -0.7, 0.7), _lerp(u[1], -0.7, 0.7), wavelength, amp, reach)
    return out


@dataclass(frozen=True)
class ReliefFamily:
    name: str
    gradient: Callable[[Tensor, Tensor, Tensor], tuple[Tensor, Tensor]]
    sample: Callable[[np.ndarray], np.ndarray]


RELIEFS: dict[str, ReliefFamily] = {
    r.name: r
    for r in (
        ReliefFamily("bumps", bumps, _sample_bumps),
        ReliefFamily("grooves", grooves, _sample_grooves),
        ReliefFamily("bevels", bevels, _sample_bevels),
        ReliefFamily("ripples", ripples, _sample_ripples),
    )
}
RELIEF_NAMES: tuple[str, ...] = tuple(RELIEFS)


def relief_normals(kind: Tensor, prm: Tensor, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Unit wall normals (three (N,) tensors) at points (x, y) of walls of relief ``kind`` (N,) (−1: flat)."""
    gx, gy = torch.zeros_like(x), torch.zeros_like(x)
    for i, name in enumerate(RELIEF_NAMES):
        idx = (kind == i).nonzero().squeeze(1)
        if idx.numel() == 0:
            continue
        a, b = RELIEFS[name].gradient(x[idx], y[idx], prm[idx])
        gx[idx], gy[idx] = a, b
    inv = torch.rsqrt(gx * gx + gy * gy + 1.0)
    return -gx * inv, -gy * inv, inv
