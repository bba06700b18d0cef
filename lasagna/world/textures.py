"""Procedural texture families: solid (3D) and painted (2D) patterns in [0, 1], on flat lists of points.

A texture is a function ``pattern(p, prm, seed) -> (N,)`` of points ``p`` (a tuple of three (N,)
tensors: object-local coordinates for objects, so the pattern sticks to the surface as the object
turns; (x, y, 0) for the wall), per-point parameters ``prm`` (N, N_PARAMS) and an integer seed (N,).
The scene turns a pattern into albedo as c₁·(lo + (1 − lo)·pattern) + Δ·(1 − pattern): colour c₁
where the pattern is 1 and c₁·lo + Δ where it is 0 (Δ = 0 gives one tinted pattern; the broadened
splits also draw a second colour, see `lasagna.world.params`).

Parameter layout (``prm`` columns): 0 frequency f (cycles per world unit; the canvas is 2 units
wide), 1–3 a unit direction u, 4–6 an offset o, 7 a duty/width fraction, 8 contrast floor lo
(used by the scene, not here), 9 an extra family-specific value.

Randomness comes from the lattice hash of `lasagna.world.noise`, so a pattern is a pure function of
its inputs: vectorised, deterministic, identical in any batch.

Families (``TEXTURES``; which split uses which is in ``lasagna.world.splits``). Solid: stripes,
checker, noise (fBm value noise), tiles (grout grid with per-tile tone), dots, marble (sine warped by
fBm), rings (wood-like rings about an axis), bricks (running bond with mortar). Painted
(`lasagna.world.paint`): deadleaves, cells, gradient, glyphs, photo, hexagons, zigzag, naturephoto, plaid,
scales, weave.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from lasagna.world import paint
from lasagna.world.noise import fbm, hash01, value_noise  # noqa: F401  (value_noise: part of this module's API)

Tensor = torch.Tensor
Vec = tuple[Tensor, Tensor, Tensor]

N_PARAMS = 10


def _scaled(p: Vec, prm: Tensor) -> Vec:
    f = prm[:, 0]
    return ((p[0] + prm[:, 4]) * f, (p[1] + prm[:, 5]) * f, (p[2] + prm[:, 6]) * f)


def _along(p: Vec, prm: Tensor) -> Tensor:
    return p[0] * prm[:, 1] + p[1] * prm[:, 2] + p[2] * prm[:, 3]


def _frac(x: Tensor) -> Tensor:
    return x - torch.floor(x)


def stripes(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Hard-edged parallel stripes across direction u; duty = fraction of each period that is bright."""
    s = _frac(_along(_scaled(p, prm), prm))
    return (s < prm[:, 7]).to(p[0].dtype)


def checker(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """A 3D checkerboard of cells 1/f wide (its traces on a surface are checks of varying shape)."""
    q = _scaled(p, prm)
    parity = (torch.floor(q[0]) + torch.floor(q[1]) + torch.floor(q[2])).remainder(2.0)
    return parity


def noise(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """fBm value noise, contrast-stretched (fBm concentrates near 0.5) and clipped to [0, 1]."""
    v = fbm(_scaled(p, prm), seed)
    return ((v - 0.5) * 2.5 + 0.5).clamp(0.0, 1.0)


def tiles(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Square tiles in the xy plane with dark grout lines (width = duty) and a hashed tone per tile."""
    q = _scaled(p, prm)
    cx, cy = torch.floor(q[0]), torch.floor(q[1])
    fx, fy = q[0] - cx, q[1] - cy
    half = 0.5 * prm[:, 7]
    grout = (fx < half) | (fx > 1.0 - half) | (fy < half) | (fy > 1.0 - half)
    tone = 0.55 + 0.45 * hash01(cx.to(torch.int64), cy.to(torch.int64), torch.zeros_like(seed), seed, q[0].dtype)
    return torch.where(grout, torch.zeros_like(tone), tone)


def dots(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Dark balls of radius duty/2 on a cubic lattice of spacing 1/f (polka dots on any surface)."""
    q = _scaled(p, prm)
    r2 = sum((_frac(c) - 0.5) ** 2 for c in q)
    rad = 0.5 * prm[:, 7]
    return (r2 > rad * rad).to(q[0].dtype)


def marble(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Veins: 0.5 + 0.5·sin(2π(f·(p·u) + k·fBm)) with turbulence k = 1 + 2·extra."""
    q = _scaled(p, prm)
    turb = 1.0 + 2.0 * prm[:, 9]
    return 0.5 + 0.5 * torch.sin(2.0 * math.pi * (_along(q, prm) + turb * fbm(q, seed, octaves=3)))


def rings(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Wood-like rings: bands of the distance from an axis along u, perturbed by fBm."""
    q = _scaled(p, prm)
    a = _along(q, prm)
    r = torch.sqrt((q[0] - a * prm[:, 1]) ** 2 + (q[1] - a * prm[:, 2]) ** 2 + (q[2] - a * prm[:, 3]) ** 2)
    return (_frac(r + 0.6 * fbm(q, seed, octaves=2)) < prm[:, 7]).to(q[0].dtype)


def bricks(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Running-bond bricks in the xy plane (1/f wide, 1/(2f) high) with mortar and a tone per brick."""
    q = _scaled(p, prm)
    y = q[1] * 2.0
    row = torch.floor(y)
    x = q[0] + 0.5 * row.remainder(2.0)
    col = torch.floor(x)
    fx, fy = x - col, y - row
    half = 0.5 * prm[:, 7]
    mortar = (fx < 0.5 * half) | (fx > 1.0 - 0.5 * half) | (fy < half) | (fy > 1.0 - half)
    tone = 0.6 + 0.4 * hash01(col.to(torch.int64), row.to(torch.int64), torch.ones_like(seed), seed, q[0].dtype)
    return torch.where(mortar, torch.zeros_like(tone), tone)


@dataclass(frozen=True)
class TextureFamily:
    """One pattern family and the ranges its parameters are drawn from."""

    name: str
    pattern: Callable[[Vec, Tensor, Tensor], Tensor]
    frequency: tuple[float, float]  # cycles per world unit
    duty: tuple[float, float]


TEXTURES: dict[str, TextureFamily] = {
    t.name: t
    for t in (
        # The training families span many scales (1–12 cycles per unit: 2.7 to 32 pixels a cycle at 64²).
        TextureFamily("stripes", stripes, (1.0, 12.0), (0.15, 0.85)),
        TextureFamily("checker", checker, (1.0, 10.0), (0.0, 0.0)),
        TextureFamily("noise", noise, (1.0, 8.0), (0.0, 0.0)),
        TextureFamily("tiles", tiles, (1.5, 8.0), (0.06, 0.25)),
        TextureFamily("dots", dots, (3.0, 7.0), (0.35, 0.7)),
        TextureFamily("marble", marble, (1.0, 3.0), (0.0, 0.0)),
        TextureFamily("rings", rings, (3.0, 8.0), (0.3, 0.6)),
        TextureFamily("bricks", bricks, (2.0, 4.0), (0.08, 0.16)),
        TextureFamily("deadleaves", paint.deadleaves, (1.0, 6.0), (0.0, 0.0)),
        TextureFamily("cells", paint.cells, (1.5, 8.0), (0.05, 0.4)),
        TextureFamily("gradient", paint.gradient, (0.4, 1.5), (0.0, 0.0)),
        TextureFamily("glyphs", paint.glyphs, (2.0, 7.0), (0.0, 0.4)),
        TextureFamily("photo", paint.photo, (0.3, 1.5), (0.0, 0.0)),
        TextureFamily("hexagons", paint.hexagons, (1.5, 7.0), (0.08, 0.3)),
        TextureFamily("zigzag", paint.zigzag, (1.5, 7.0), (0.3, 0.7)),
        TextureFamily("naturephoto", paint.naturephoto, (0.3, 1.5), (0.0, 0.0)),
        # The select split's (appended: every earlier index is unchanged).
        TextureFamily("plaid", paint.plaid, (1.0, 6.0), (0.2, 0.5)),
        TextureFamily("scales", paint.scales, (2.0, 7.0), (0.08, 0.25)),
        TextureFamily("weave", paint.weave, (1.5, 5.0), (0.2, 0.45)),
    )
}
TEXTURE_NAMES: tuple[str, ...] = tuple(TEXTURES)


def sample_params(family: str, u: np.ndarray, lo: float) -> np.ndarray:
    """Map 8 uniforms to a parameter row of ``family``; ``lo`` is the contrast floor chosen by the scene."""
    fam = TEXTURES[family]
    out = np.zeros(N_PARAMS)
    out[0] = fam.frequency[0] + (fam.frequency[1] - fam.frequency[0]) * u[0]
    # A uniform direction on the sphere (Archimedes: z uniform in [−1, 1], azimuth uniform).
    z = 2.0 * u[1] - 1.0
    phi = 2.0 * math.pi * u[2]
    rho = math.sqrt(max(0.0, 1.0 - z * z))
    out[1:4] = (rho * math.cos(phi), rho * math.sin(phi), z)
    out[4:7] = 10.0 * u[3:6]
    out[7] = fam.duty[0] + (fam.duty[1] - fam.duty[0]) * u[6]
    out[8] = lo
    out[9] = u[7]
    return out


def evaluate(surface: Tensor, family: Tensor, p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Pattern values (N,) at points ``p`` of surfaces ``surface`` (N,), grouped by texture family.

    ``family`` (S,), ``prm`` (S, N_PARAMS) and ``seed`` (S,) describe the S surfaces; each family
    runs once on the points whose surface uses it, so no point pays for another family's pattern.
    """
    out = torch.zeros_like(p[0])
    fam = family[surface]
    for i, name in enumerate(TEXTURE_NAMES):
        idx = (fam == i).nonzero().squeeze(1)
        if idx.numel() == 0:
            continue
        srf = surface[idx]
        out[idx] = TEXTURES[name].pattern((p[0][idx], p[1][idx], p[2][idx]), prm[srf], seed[srf])
    return out
