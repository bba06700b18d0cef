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
