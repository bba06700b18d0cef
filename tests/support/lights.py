"""numpy float64 references of the lights a surface layer may have, from their closed forms alone (no lasagna)."""

from __future__ import annotations

import numpy as np


def spot_reference(n, x, y, z, cone, ax, ay, blend):
    """numpy float64 of a spot light over unit normals n (3, h, w): the point light's closed form times Blender's
    spot mask, smoothstep((cos θ − cos C)/(b·(1 − cos C))) (a step at b = 0), θ between the ray from the light to
    the pixel and the axis from the light to (ax, ay) on the map."""
    _, h, w = n.shape
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
    return 0.25 + 0.75 * (z / r) ** 2 * mask * np.maximum(0.0, (n * d / r).sum(0))
