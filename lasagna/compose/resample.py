"""Resampling between an image's size and a learned layer's working size.

Learned shading and light are low-frequency: a generator (or a per-image layer) works at a fixed
*working size* — the size it was trained at — and its layer is brought to the image's size here, so
an edit's quality does not depend on the image's resolution (a fully convolutional network applied
at 8× its training size sees every edge as a feature of its receptive field: an emboss filter).

- ``working_size(h, w, side)``: the largest size with the image's aspect whose long side is ``side``
  (never larger than the image; the image's own size for ``side=None``);
- ``downsample(x, size)``: antialiased (area-weighted) reduction, the base as the generator sees it;
- ``upsample(y, size)``: bilinear enlargement of a layer (smooth, so no texture of the base enters it).
  For shading and light a guided enlargement was tried and not kept: it sharpens silhouettes but also
  copies the base's texture edges into the layer.
- ``guided_upsample(y, guide)``: the fast guided filter (He & Sun 2015, "Fast Guided Filter", Alg. 2; the
  guided filter of He, Sun & Tang 2013, eq. 5–8): a local linear model y ≈ a·I + b fitted at the working
  size and applied to the full-size guide I, so the layer's edges follow the guide's.
- ``upsample_colour(layer, y)``: a colour-over-luminance layer (RGB, or RGBA with alpha last) enlarged to
  the size of the full-size luma ``y``: its colour by ``guided_upsample`` with ``y`` as the guide, then set to
  luma ``y`` (``compose.color.set_luma``); its alpha bilinearly. Colour is what *should* follow the base's
  edges: Levin, Lischinski & Weiss (2004, "Colorization using Optimization") colourise on exactly this
  premise — neighbouring pixels of similar luminance have similar colour — and the guided filter's local
  linear model is its closed form. A bilinear enlargement would smear a 32² layer's colour 16 pixels
  across every edge of a 512² photo.
- ``joint_bilateral_upsample(y, guide)``: joint bilateral upsampling (Kopf, Cohen, Lischinski & Uyttendaele 2007,
  eq. 2): each full-size pixel the mean of the working-size values of the cells about it, weighted by a Gaussian of
  the distance to each cell and a Gaussian of the difference between the pixel's guide and the cell's. The output is
  a convex combination of values the layer already has (no a·I + b: the guide's texture is not copied in), whose
  edges follow the guide's — a surface layer's normals enlarged so an object's rim stops at the photograph's edge
  instead of spilling a working pixel's width into a sky (docs/BENCHMARKS.md, round 21).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from lasagna.compose.color import set_luma

Tensor = torch.Tensor

GUIDED_RADIUS = 1
"""Window radius of the guided filter at the working size: 3×3 working pixels, the smallest window with a
slope to fit; a 32² layer's window then spans ~3/32 of the image."""

GUIDED_EPS = 1e-3
"""ε of the guided filter (guide in [0, 1]): a window whose guide variance is below ε is treated as flat (its
layer is smoothed, not sharpened). 1e-3 ≈ σ of 0.03, a texture of low contrast."""


JBU_CELLS = 4
"""Cells per side of the window ``joint_bilateral_upsample`` averages: the 4×4 working-size cells nearest each
full-size pixel (the two on each side of it), enough for a Gaussian of σ one cell."""

JBU_SIGMA_CELLS = 1.0
"""σ of the spatial Gaussian of ``joint_bilateral_upsample``, in working-size cells."""

JBU_SIGMA_GUIDE = 0.1
"""σ of the range Gaussian of ``joint_bilateral_upsample`` on the guide (luma in [0, 1]): chosen by looking at the
photograph selection set (docs/BENCHMARKS.md, round 21) — 0.05 broke the relief into blocks and took in foliage's
speckle; 0.1 stops a head's rim at its edge against a sky."""

JBU_MAX_SIDE = 1024
"""The longest side ``joint_bilateral_upsample`` works at: a larger guide is reduced to it (``working_size``), the mean
taken there and enlarged the rest of the way bilinearly. Its cost is 16 full-size passes (8 s at 4096² on the
project's 2-core CPU against 0.09 s at 512²); at 1024 a rim still stops within 1/1024 of the image's side of its
edge, far inside the working size's 1/32 that the mean exists to remove."""

JBU_WEIGHT_FLOOR = 1e-30
"""Floor of the summed weights of ``joint_bilateral_upsample``: a guard only — each pixel's own cell weighs at least
exp(−1/σ²)·exp(−1/2σ_g²), about 1e-22 for a guide in [0, 1] at the default σs, far above it in float32."""


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


def _box(x: Tensor, r: int) -> Tensor:
    """Mean over the (2r + 1)² window about each pixel, the window clipped at the borders."""
    return F.avg_pool2d(x, 2 * r + 1, stride=1, padding=r, count_include_pad=False)


def guided_upsample(y: Tensor, guide: Tensor, radius: int = GUIDED_RADIUS, eps: float = GUIDED_EPS) -> Tensor:
    """The fast guided filter: y (B, C, h, w) at the working size, guide (B, 1, H, W) at full size → (B, C, H, W).

    1. I = the guide reduced to (h, w) (``downsample``); 2. per window at (h, w): a = cov(I, y)/(var(I) + ε),
    b = mean(y) − a·mean(I) (eq. 5–6), averaged over the windows covering each pixel (eq. 8); 3. a and b
    enlarged bilinearly to (H, W); output a·guide + b.
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


def upsample_colour(layer: Tensor, y: Tensor) -> Tensor:
    """A colour-over-luminance layer (B, 3 or 4, h, w) enlarged to ``y``'s size (B, 1, H, W), ``y`` the full-size
    luma it carries (module docstring): colour = set_luma(guided_upsample(set_luma(C, y_w), y), y) with y_w = y
    reduced to (h, w); alpha (last) enlarged bilinearly. The colour's luma is ``y`` exactly; values in [0, 1]. At
    equal sizes nothing is filtered: set_luma(C, y)."""
    if tuple(layer.shape[-2:]) == tuple(y.shape[-2:]):
        colour = set_luma(layer[:, :3], y)
    else:
        colour = set_luma(guided_upsample(set_luma(layer[:, :3], downsample(y, tuple(layer.shape[-2:]))), y), y)
    colour = colour.clamp(0.0, 1.0)  # ClipColor lands on 0 and 1 only up to rounding (−7e-18 seen in float64)
    if layer.shape[1] == 3:
        return colour
    return torch.cat([colour, upsample(layer[:, 3:], tuple(y.shape[-2:])).clamp(0.0, 1.0)], dim=1)


def gaussian_blur(x: Tensor, sigma: float) -> Tensor:
    """A separable Gaussian blur of ``x`` (B, C, H, W), σ in pixels, edges mirrored (radius 3σ, at most a side − 1).
    Along a side of one pixel it is the identity (one sample, mirrored, is itself; a mirror pad needs two)."""
    c = x.shape[1]
    for dim in (-1, -2):
        if x.shape[dim] == 1:
            continue
        r = max(1, min(int(math.ceil(3 * sigma)), x.shape[dim] - 1))
        t = torch.arange(-r, r + 1, dtype=x.dtype, device=x.device)
        k = torch.exp(-0.5 * (t / sigma) ** 2)
        k = (k / k.sum()).repeat(c, 1, 1)
        if dim == -1:
            x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="reflect"), k[:, :, None, :], groups=c)
        else:
            x = F.conv2d(F.pad(x, (0, 0, r, r), mode="reflect"), k[:, :, :, None], groups=c)
    return x


def joint_bilateral_upsample(
    y: Tensor, guide: Tensor, sigma: float = JBU_SIGMA_CELLS, sigma_guide: float = JBU_SIGMA_GUIDE
) -> Tensor:
    """Joint bilateral upsampling (module docstring): y (B, C, h, w) at the working size, guide (B, 1, H, W) at full
    size → (B, C, H, W). With (u, v) a full-size pixel's centre in working-size cell coordinates and q each of the
    ``JBU_CELLS``² cells about it (clamped at the borders), out = Σ_q y_q·w_q / Σ_q w_q, w_q = exp(−‖(u, v) − q‖² /
    2σ²)·exp(−(I − Ĩ_q)² / 2σ_g²), Ĩ the guide reduced to (h, w) (``downsample``). At equal sizes: y; a guide longer
    than ``JBU_MAX_SIDE`` is reduced to it first and the result enlarged bilinearly."""
    h, w = y.shape[-2:]
    size = tuple(guide.shape[-2:])
    if (h, w) == size:
        return y
    if max(size) > JBU_MAX_SIDE:  # the mean at JBU_MAX_SIDE, the rest bilinearly (JBU_MAX_SIDE)
        capped = working_size(*size, JBU_MAX_SIDE)
        return upsample(joint_bilateral_upsample(y, downsample(guide, capped), sigma, sigma_guide), size)
    small = downsample(guide, (h, w)).to(y.dtype)
    guide = guide.to(y.dtype)
    u = (torch.arange(size[0], dtype=y.dtype, device=y.device) + 0.5) * h / size[0] - 0.5
    v = (torch.arange(size[1], dtype=y.dtype, device=y.device) + 0.5) * w / size[1] - 0.5
    cu, cv = u.floor().long(), v.floor().long()
    num = torch.zeros((*y.shape[:2], *size), dtype=y.dtype, device=y.device)
    den = torch.zeros((y.shape[0], 1, *size), dtype=y.dtype, device=y.device)
    offsets = range(1 - JBU_CELLS // 2, JBU_CELLS // 2 + 1)
    for dy in offsets:
        rows = (cu + dy).clamp(0, h - 1)
        wy = torch.exp(-((u - (cu + dy).to(y.dtype)) ** 2) / (2 * sigma**2))
        for dx in offsets:
            cols = (cv + dx).clamp(0, w - 1)
            wx = torch.exp(-((v - (cv + dx).to(y.dtype)) ** 2) / (2 * sigma**2))
            cell = small[:, :, rows][:, :, :, cols]
            weight = wy[:, None] * wx[None, :] * torch.exp(-((guide - cell) ** 2) / (2 * sigma_guide**2))
            num += weight * y[:, :, rows][:, :, :, cols]
            den += weight
    return num / den.clamp_min(JBU_WEIGHT_FLOOR)
