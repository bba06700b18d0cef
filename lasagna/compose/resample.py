"""Resampling between an image's size and a learned layer's working size.

Learned shading and light are low-frequency: a generator (or a per-image layer) works at a fixed
*working size* — the size it was trained at — and its layer is brought to the image's size here, so
an edit's quality does not depend on the image's resolution (a fully convolutional network applied
at 8× its training size sees every edge as a feature of its receptive field: an emboss filter).

- ``working_size(h, w, side)``: the largest size with the image's aspect whose long side is ``side``
  (never larger than the image; the image's own size for ``side=None``);
- ``downsample(x, size)``: antialiased (area-weighted) reduction, the base as the generator sees it;
- ``upsample(y, size)``: bilinear enlargement of a layer (smooth, so no texture of the base enters it).
  A guided enlargement (He & Sun's fast guided filter, the base as guide) was tried and not kept: it
  sharpens silhouettes but also copies the base's texture edges into the layer.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

Tensor = torch.Tensor


def working_size(h: int, w: int, side: int | None) -> tuple[int, int]:
    """(h', w') with h'/w' ≈ h/w, max(h', w') = min(side, max(h, w)), each ≥ 1; (h, w) for side None."""
    if side is None:
        return h, w
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
