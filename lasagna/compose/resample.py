"""Resampling between an image's size and a learned layer's working size.

Learned shading and light are low-frequency: a generator (or a per-image layer) works at a fixed
*working size* — the size it was trained at — and its layer is brought to the image's size here, so
an edit's quality does not depend on the image's resolution (a fully convolutional network applied
at 8× its training size sees every edge as a feature of its receptive field: an emboss filter).

- ``working_size(h, w, side)``: the largest size with the image's aspect whose long side is ``side``
  (never larger than the image);
- ``downsample(x, size)``: antialiased (area-weighted) reduction, the base as the generator sees it;
- ``upsample(y, size)``: bilinear enlargement of a layer (smooth, so no texture of the base enters it);
- ``guided_upsample(y, guide, size, radius, eps)``: the fast guided filter (He & Sun 2015, "Fast
  Guided Filter", Alg. 2; the guided filter of He, Sun & Tang 2013, eq. 5–8): a local linear model
  y ≈ a·I + b fitted at the working size and applied to the full-size guide I, so the layer's edges
  follow the guide's. It restores sharp silhouettes and also copies strong texture edges of the guide
  into the layer; ``benchmarks/generalisation.py`` measures which wins.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

Tensor = torch.Tensor

GUIDED_EPS = 1e-3
"""Default ε of the guided filter (guide in [0, 1]): a window whose guide variance is below ε is
treated as flat (its layer is smoothed, not sharpened). 1e-3 ≈ σ of 0.03, a texture of low contrast."""


def working_size(h: int, w: int, side: int) -> tuple[int, int]:
    """(h', w') with h'/w' ≈ h/w, max(h', w') = min(side, max(h, w)), each ≥ 1."""
    if side < 1:
        raise ValueError(f"working side must be ≥ 1, got {side}")
    scale = min(1.0, side / max(h, w))
    return max(1, round(h * scale)), max(1, round(w * scale))


def downsample(x: Tensor, size: tuple[int, int]) -> Tensor:
    """(B, C, H, W) → (B, C, *size) with an antialiasing filter (identity when the size is equal)."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x, size=size, mode="bilinear", align_corners=False, antialias=True)


def upsample(y: Tensor, size: tuple[int, int]) -> Tensor:
    """(B, C, h, w) → (B, C, *size), bilinear with pixel centres aligned (identity when equal)."""
    if tuple(y.shape[-2:]) == tuple(size):
        return y
    return F.interpolate(y, size=size, mode="bilinear", align_corners=False)


def _box(x: Tensor, r: int) -> Tensor:
    """Mean over the (2r + 1)² window about each pixel, the window clipped at the borders."""
    return F.avg_pool2d(x, 2 * r + 1, stride=1, padding=r, count_include_pad=False)


def guided_upsample(y: Tensor, guide: Tensor, radius: int = 1, eps: float = GUIDED_EPS) -> Tensor:
    """The fast guided filter: y (B, C, h, w) at the working size, guide (B, 1, H, W) at full size.

    1. I = the guide reduced to (h, w); 2. per window at (h, w): a = cov(I, y)/(var(I) + ε),
    b = mean(y) − a·mean(I) (eq. 5–6), averaged over the windows covering each pixel (eq. 8);
    3. a and b enlarged bilinearly to (H, W); output a·guide + b.
    """
    size = tuple(guide.shape[-2:])
    g = downsample(guide, tuple(y.shape[-2:]))
    mean_i, mean_y = _box(g, radius), _box(y, radius)
    cov = _box(g * y, radius) - mean_i * mean_y
    var = _box(g * g, radius) - mean_i * mean_i
    a = cov / (var.clamp_min(0.0) + eps)
    b = mean_y - a * mean_i
    a, b = _box(a, radius), _box(b, radius)
    return upsample(a, size) * guide + upsample(b, size)
