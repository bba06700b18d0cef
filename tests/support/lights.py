"""numpy float64 references of the lights a surface layer may have, from their closed forms alone (no lasagna)."""

from __future__ import annotations

import numpy as np


def spot_field(shape, x, y, z, cone, ax, ay, blend):
    """(unit vectors l (3, h, w) from each pixel to a spot light, its weight (z/|d|)²·m (h, w)) over a map of ``shape``
    (…, h, w): the point light's closed form times Blender's spot mask m = smoothstep((cos θ − cos C)/(b·(1 − cos C)))
    (a step at b = 0), θ between the ray from the light to the pixel and the axis from the light to (ax, ay)."""
    h, w = shape[-2:]
    side = max(h, w)
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    d = np.stack([(x - (jj + 0.5) / w) * w / side, ((ii + 0.5) / h - y) * h / side, np.full((h, w), z)])
    r = np.linalg.norm(d, axis=0)
    axis = np.array([(x - ax) * w / side, (ay - y) * h / side, z])
    cos = (d * (axis / np.linalg.norm(axis))[:, None, None]).sum(0) / r
    edge = np.cos(np.radians(cone))
    if blend == 0:
        mask = (cos > edge).astype(float)
    else:
        t = np.clip((cos - edge) / (blend * (1 - edge)), 0, 1)
        mask = t * t * (3 - 2 * t)
    return d / r, (z / r) ** 2 * mask


def spot_reference(n, x, y, z, cone, ax, ay, blend):
    """numpy float64 of a spot light's shading over unit normals n (3, h, w), a = 0.25: a + (1 − a)·f·max(0, n·l)."""
    l_vec, weight = spot_field(n.shape, x, y, z, cone, ax, ay, blend)
    return 0.25 + 0.75 * weight * np.maximum(0.0, (n * l_vec).sum(0))


def blinn_phong(n, l_vec, p):
    """numpy float64 of the Blinn–Phong highlight max(0, n·h)^p·[n·l > 0] over unit normals n (3, h, w), ``l_vec`` one
    unit light (3,) or one per pixel (3, h, w), h the half vector of l and the view +z."""
    lv = l_vec if l_vec.ndim == 3 else l_vec[:, None, None]
    half = lv + np.array([0.0, 0.0, 1.0])[:, None, None]
    half = half / np.linalg.norm(half, axis=0, keepdims=True)
    return np.maximum(0.0, (n * half).sum(0)) ** p * ((n * lv).sum(0) > 0)


def _bilinear(h, col, row):
    """numpy float64 bilinear sample of a height field h (H, W) at pixel coordinates (col, row), edges clamped."""
    hh, ww = h.shape
    col, row = np.clip(col, 0, ww - 1), np.clip(row, 0, hh - 1)
    c0, r0 = np.minimum(np.floor(col).astype(int), ww - 2), np.minimum(np.floor(row).astype(int), hh - 2)
    fc, fr = col - c0, row - r0
    return (
        h[r0, c0] * (1 - fc) * (1 - fr)
        + h[r0, c0 + 1] * fc * (1 - fr)
        + h[r0 + 1, c0] * (1 - fc) * fr
        + h[r0 + 1, c0 + 1] * fc * fr
    )


def directional_shadow(h, l_vec, step=0.25, eps=1e-3):
    """numpy float64 visibility (H, W) in {0, 1} of a directional light over heights h (H, W; canvas units, the canvas
    2 wide, y up): from each pixel's surface point a ray toward ``l_vec`` marched ``step`` pixels at a time across the
    image until it leaves the map, blocked where the (bilinear) heights rise above it by more than ``eps``."""
    hh, ww = h.shape
    lx, ly, lz = l_vec
    across = np.hypot(lx, ly)
    if across < 1e-9:
        return np.ones_like(h)
    dc, dr, rise = lx / across, -ly / across, (2.0 / ww) * lz / across
    rows, cols = np.meshgrid(np.arange(hh, dtype=float), np.arange(ww, dtype=float), indexing="ij")
    blocked = np.zeros(h.shape, dtype=bool)
    k = step
    while True:
        col, row = cols + k * dc, rows + k * dr
        inside = (col >= -0.5) & (col <= ww - 0.5) & (row >= -0.5) & (row <= hh - 0.5)
        if not inside.any():
            return (~blocked).astype(float)
        blocked |= inside & (_bilinear(h, col, row) > h + k * rise + eps)
        k += step


def point_shadow(h, x, y, z, step=0.25, eps=1e-3):
    """numpy float64 visibility (H, W) in {0, 1} of a point light at (x, y) (fractions of the map from its top-left),
    z (units of its longer side) above the heights' zero, over heights h (canvas units): each pixel's segment to the
    light marched ``step`` pixels at a time, blocked where the heights inside the map rise above it by more than
    ``eps``."""
    hh, ww = h.shape
    per_pixel = ww / 2.0
    ground = h * per_pixel
    lc, lr, lzp = x * ww - 0.5, y * hh - 0.5, z * max(hh, ww)
    rows, cols = np.meshgrid(np.arange(hh, dtype=float), np.arange(ww, dtype=float), indexing="ij")
    length = np.hypot(lc - cols, lr - rows)
    blocked = np.zeros(h.shape, dtype=bool)
    k = step
    while (k < length).any():
        f = np.minimum(k / np.maximum(length, 1e-9), 1.0)
        col, row = cols + f * (lc - cols), rows + f * (lr - rows)
        inside = (col >= -0.5) & (col <= ww - 0.5) & (row >= -0.5) & (row <= hh - 0.5) & (k < length)
        blocked |= inside & (_bilinear(ground, col, row) > ground + f * (lzp - ground) + eps * per_pixel)
        k += step
    return (~blocked).astype(float)


def sky_share(h, azimuths=12, elevations=3):
    """numpy float64 ambient visibility (H, W) of heights h: the mean of ``directional_shadow`` over ``azimuths`` ×
    ``elevations`` directions, azimuths (j + ½)·360°/``azimuths``, elevations from the view axis asin √((k + ½)/
    ``elevations``) — equal shares of a cosine-weighted sky."""
    total = np.zeros_like(h)
    for k in range(elevations):
        el = np.arcsin(np.sqrt((k + 0.5) / elevations))
        for j in range(azimuths):
            az = np.radians(360.0 * (j + 0.5) / azimuths)
            l_vec = (np.sin(el) * np.cos(az), np.sin(el) * np.sin(az), np.cos(el))
            total += directional_shadow(h, l_vec)
    return total / (azimuths * elevations)
