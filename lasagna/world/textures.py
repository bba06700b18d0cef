"""Procedural texture families: solid (3D) patterns in [0, 1], evaluated on flat lists of points.

A texture is a function ``pattern(p, prm, seed) -> (N,)`` of points ``p`` (a tuple of three (N,)
tensors: object-local coordinates for objects, so the pattern sticks to the surface as the object
turns; (x, y, 0) for the wall), per-point parameters ``prm`` (N, N_PARAMS) and an integer seed (N,).
The scene turns a pattern into albedo as colour × (lo + (1 − lo)·pattern).

Parameter layout (``prm`` columns): 0 frequency f (cycles per world unit; the canvas is 2 units
wide), 1–3 a unit direction u, 4–6 an offset o, 7 a duty/width fraction, 8 contrast floor lo
(used by the scene, not here), 9 an extra family-specific value.

Random values come from an integer hash of lattice coordinates and the seed (coordinates spread by
large primes, then a murmur3-style 32-bit finaliser, computed in int64), not from a random-number generator, so a pattern is a pure
function of its inputs: vectorised, deterministic, identical in any batch.

Families (``TEXTURES``; which split uses which is in ``lasagna.world.splits``):
stripes, checker, noise (fBm value noise), tiles (grout grid with per-tile tone), dots, marble
(sine warped by fBm), rings (wood-like rings about an axis), bricks (running bond with mortar).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

Tensor = torch.Tensor
Vec = tuple[Tensor, Tensor, Tensor]

N_PARAMS = 10
_M32 = 0xFFFFFFFF
_MIX = 0x45D9F3B  # < 2**31, so a 32-bit value times it fits in int64 without overflow
# Large odd multipliers (< 2**31) spreading lattice coordinates before the finaliser (Teschner et
# al. 2003, "Optimized spatial hashing", use the same idea with these primes).
_PX, _PY, _PZ = 73856093, 19349663, 83492791


def _mix(h: Tensor) -> Tensor:
    """A 32-bit integer finaliser (two xor-shift-multiply rounds) on int64 tensors."""
    h = h & _M32  # a new tensor; the rest works in place on it (this is the hot loop of fBm)
    for _ in range(2):
        h.bitwise_xor_(h >> 16).mul_(_MIX).bitwise_and_(_M32)
    return h.bitwise_xor_(h >> 16)


def _lattice_key(ix: Tensor, iy: Tensor, iz: Tensor, seed: Tensor) -> Tensor:
    # Linear in the coordinates, so neighbouring lattice points are one integer add away.
    return _mix(seed) + ix * _PX + iy * _PY + iz * _PZ


def _unit(h: Tensor, dtype: torch.dtype) -> Tensor:
    # The top 24 bits are exact in float32, so the value is in [0, 1) in every float dtype.
    return (h >> 8).to(dtype) * (1.0 / 16777216.0)


def hash01(ix: Tensor, iy: Tensor, iz: Tensor, seed: Tensor, dtype: torch.dtype = torch.float32) -> Tensor:
    """A uniform-looking value in [0, 1) for each integer lattice point and seed."""
    return _unit(_mix(_lattice_key(ix, iy, iz, seed)), dtype)


def value_noise(p: Vec, seed: Tensor) -> Tensor:
    """3D value noise: trilinear interpolation of hashed lattice values with smoothstep weights."""
    cells = [torch.floor(c) for c in p]
    frac = [c - f for c, f in zip(p, cells)]
    w = [f * f * (3.0 - 2.0 * f) for f in frac]
    key = _lattice_key(cells[0].to(torch.int64), cells[1].to(torch.int64), cells[2].to(torch.int64), seed)

    def corner(dx: int, dy: int, dz: int) -> Tensor:
        return _unit(_mix(key + (dx * _PX + dy * _PY + dz * _PZ)), p[0].dtype)

    # Trilinear interpolation as seven lerps: along z, then y, then x.
    yz = [[torch.lerp(corner(dx, dy, 0), corner(dx, dy, 1), w[2]) for dy in (0, 1)] for dx in (0, 1)]
    x0 = torch.lerp(yz[0][0], yz[0][1], w[1])
    x1 = torch.lerp(yz[1][0], yz[1][1], w[1])
    return torch.lerp(x0, x1, w[0])


def fbm(p: Vec, seed: Tensor, octaves: int = 4) -> Tensor:
    """Fractal Brownian motion: octaves of value noise at doubling frequency, halving amplitude; in [0, 1]."""
    total, amp, norm = torch.zeros_like(p[0]), 1.0, 0.0
    for k in range(octaves):
        scale = 2.0**k
        # A fixed per-octave shift decorrelates the lattices (all octaves share the origin otherwise).
        q = (p[0] * scale + 17.3 * k, p[1] * scale + 5.1 * k, p[2] * scale + 11.7 * k)
        total = total + amp * value_noise(q, seed + k)
        norm += amp
        amp *= 0.5
    return total / norm


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
        TextureFamily("stripes", stripes, (2.0, 7.0), (0.3, 0.7)),
        TextureFamily("checker", checker, (2.0, 6.0), (0.0, 0.0)),
        TextureFamily("noise", noise, (2.0, 5.0), (0.0, 0.0)),
        TextureFamily("tiles", tiles, (2.0, 5.0), (0.08, 0.2)),
        TextureFamily("dots", dots, (3.0, 7.0), (0.35, 0.7)),
        TextureFamily("marble", marble, (1.0, 3.0), (0.0, 0.0)),
        TextureFamily("rings", rings, (3.0, 8.0), (0.3, 0.6)),
        TextureFamily("bricks", bricks, (2.0, 4.0), (0.08, 0.16)),
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
