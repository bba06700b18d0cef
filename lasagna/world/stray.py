"""Stray illumination: brightness in a lit image that is not relief under the key light.

Photographs carry light the world's contract does not: a sky that glows toward the horizon, a lens's
vignette, the pool of a spotlight on a backdrop. A lit-input surface estimator trained only on the contract
(image = albedo × (a + (1 − a)·max(0, n·l))) reads every such gradient as relief or as the key light: the
rocket photograph's night sky becomes a bowl, and its relight turns the wrong way (issue #24, round 8's
sheets). Here such light is drawn as a smooth positive gain G per scene, multiplied onto the lit image
(clamped to [0, 1], as a sensor clips), while the truth the estimator is taught — normals, the source
light's shading, the silhouettes — stays the scene's own: G is, for the estimator, paint.

Three kinds, one drawn uniformly per scene, on coordinates x, y ∈ [−1, 1] (x right, y down; the window's
long side spans [−1, 1]):

- **gradient** (a sky, a window's falloff): G = exp(s·(x cos θ + y sin θ)), θ uniform, s uniform in
  ``GRADIENT_LOG_SLOPE``;
- **vignette**: G = 1 − v·(x² + y²)/2, v uniform in ``VIGNETTE_DEPTH`` (the corners darkened by v);
- **pool** (a spotlight on the backdrop): G = 1 + b·exp(−|p − c|²/(2σ²)), c uniform in [−1, 1]², σ uniform in
  ``POOL_WIDTH``, b uniform in ``POOL_GAIN``.

With probability ``WALLS_ONLY`` the gain falls on the walls only (G on the background, 1 on the objects' mask:
a sky behind the objects), else on the whole image (a vignette, a pool across everything). Every draw comes
from the caller's generator, so a training run that uses it resumes bit for bit.
"""

from __future__ import annotations

import math

import torch

GRADIENT_LOG_SLOPE = (0.2, 0.8)
"""Range of s: the log-gain per unit of x (half the frame); at 0.8 one edge is e^1.6 ≈ 5× the other."""
VIGNETTE_DEPTH = (0.2, 0.6)
"""Range of v: the fraction of brightness the corners lose."""
POOL_WIDTH = (0.25, 0.75)
"""Range of σ, in units of half the frame."""
POOL_GAIN = (0.3, 1.5)
"""Range of b: the pool's centre is 1 + b times as bright as far from it."""
WALLS_ONLY = 0.5
"""Probability that the gain falls on the background only."""
KINDS = ("gradient", "vignette", "pool")


def _uniform(count: int, bounds: tuple[float, float], rng: torch.Generator) -> torch.Tensor:
    lo, hi = bounds
    return lo + (hi - lo) * torch.rand(count, generator=rng, dtype=torch.float64)


def stray_gain(mask: torch.Tensor, rng: torch.Generator, probability: float = 1.0) -> torch.Tensor:
    """(B, 1, H, W) positive gains for scenes whose objects' mask is ``mask`` (B, 1, H, W): each scene, with
    ``probability``, one of the module's kinds; otherwise 1 everywhere. Same dtype and device as ``mask``; every
    random number drawn from ``rng`` (on the CPU), the same count whatever the outcome."""
    b, _, h, w = mask.shape
    scale = 2.0 / max(h, w)
    ys = (torch.arange(h, dtype=torch.float64) + 0.5 - h / 2) * scale
    xs = (torch.arange(w, dtype=torch.float64) + 0.5 - w / 2) * scale
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    kind = torch.randint(0, len(KINDS), (b,), generator=rng)
    theta = _uniform(b, (0.0, 2 * math.pi), rng)
    slope = _uniform(b, GRADIENT_LOG_SLOPE, rng)
    depth = _uniform(b, VIGNETTE_DEPTH, rng)
    cx, cy = _uniform(b, (-1.0, 1.0), rng), _uniform(b, (-1.0, 1.0), rng)
    width = _uniform(b, POOL_WIDTH, rng)
    pool = _uniform(b, POOL_GAIN, rng)
    walls_only = torch.rand(b, generator=rng, dtype=torch.float64) < WALLS_ONLY
    on = torch.rand(b, generator=rng, dtype=torch.float64) < probability

    def per(v: torch.Tensor) -> torch.Tensor:
        return v[:, None, None]

    gradient = torch.exp(per(slope) * (x * per(theta.cos()) + y * per(theta.sin())))
    vignette = 1.0 - per(depth) * (x * x + y * y) / 2
    far2 = (x - per(cx)) ** 2 + (y - per(cy)) ** 2
    spot = 1.0 + per(pool) * torch.exp(-far2 / (2 * per(width) ** 2))
    gain = torch.where(per(kind == 0), gradient, torch.where(per(kind == 1), vignette, spot))
    gain = torch.where(per(on), gain, torch.ones_like(gain))[:, None].to(dtype=mask.dtype, device=mask.device)
    walls = per(walls_only)[:, None].to(mask.device)
    return torch.where(walls, mask + (1 - mask) * gain, gain)
