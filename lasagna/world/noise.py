"""Integer lattice hashing and value noise: the random source of every procedural pattern.

Random values come from an integer hash of lattice coordinates and a seed (coordinates spread by
large primes, then a murmur3-style 32-bit finaliser, computed in int64), not from a random-number
generator, so a pattern is a pure function of its inputs: vectorised, deterministic, identical in any
batch.
"""

from __future__ import annotations

import torch

Tensor = torch.Tensor
Vec = tuple[Tensor, Tensor, Tensor]
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
