"""Hand-built scenes for the world tests: one object at a known place, so closed forms apply."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from lasagna.world.params import SceneParams, sample_scenes
from lasagna.world.shapes import SHAPE_NAMES, SHAPES


def pixel_centres(h: int, w: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y) float64 grids of the camera-frame pixel centres, row 0 at the top (y = +1 edge)."""
    w = h if w is None else w
    xs = -1.0 + (np.arange(w) + 0.5) * 2.0 / w
    ys = 1.0 - (np.arange(h) + 0.5) * 2.0 / h
    return np.meshgrid(xs, ys)


def single_object(
    shape: str,
    size: tuple[float, float, float],
    center: tuple[float, float, float] = (0.0, 0.0, 0.0),
    rotation: np.ndarray | None = None,
    label: str = "left",
) -> SceneParams:
    """Scene 0 of train/seed 0 with its first slot replaced by the given object, the others removed, a flat wall."""
    p = sample_scenes("train", 0, [0]).walls_only()  # no other object, a flat wall
    f64 = torch.float64
    present = torch.zeros_like(p.present)
    present[0, 0] = True
    shp = p.shape.clone()
    shp[0, 0] = SHAPE_NAMES.index(shape)
    sz = p.size.clone()
    sz[0, 0] = torch.tensor(size, dtype=f64)
    c = p.center.clone()
    c[0, 0] = torch.tensor(center, dtype=f64)
    r = p.rotation.clone()
    r[0, 0] = torch.eye(3, dtype=f64) if rotation is None else torch.as_tensor(rotation, dtype=f64)
    rad = p.radius.clone()
    rad[0, 0] = SHAPES[shape].bounding_radius(np.asarray(size))
    return dataclasses.replace(p, present=present, shape=shp, size=sz, center=c, rotation=r, radius=rad).with_labels(
        label
    )
