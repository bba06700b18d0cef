"""Pattern fills: a tile repeated over a rectangle, by modular indexing, at a scale.

The tiling is psd-tools' ``draw_pattern_fill`` (``psd_tools/composite/paint.py``), which models Photoshop's pattern
fill layers:

1. at a scale s ≠ 100 % the tile (th, tw) is resampled to (max(1, ⌊th·s/100⌋), max(1, ⌊tw·s/100⌋)) with Pillow's
   bilinear filter, each channel on its own (alpha is not premultiplied): a triangle of support max(1, 1/r) at the
   ratio r, weights normalised where the support leaves the tile (``F.interpolate(..., antialias=True)`` is that
   filter);
2. the tiling's origin (ox, oy) is the anchor's corner — the layer's rectangle with ``align``, else the canvas's —
   plus the phase (whole pixels; psd-tools reads none, so its tiling starts at the layer's corner);
3. canvas pixel (x, y) is tile[(y − oy) mod th′, (x − ox) mod tw′].

Resampled in float64 and cast once; the fill is differentiable in the tile (an index select of a linear map).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from lasagna.compose.layer import LayerTensors
from lasagna.document.pattern import scaled_side, tile_problem
from lasagna.errors import LasagnaError

Box = tuple[int, int, int, int]  # (x0, y0, x1, y1) in canvas pixels


@dataclass(eq=False)
class TileTensors(LayerTensors):
    """A pattern layer's stored tensors: its tile's colour ``(C, th, tw)`` and alpha, and the mask of the layer's
    rectangle ``(1, h, w)`` (or None) — the one ``LayerTensors`` whose mask is not its colour's size. The stack
    holds it; the plan tiles the colour over the rectangle (``plan.pattern_tensors``) and blends that."""

    def validate(self) -> None:
        LayerTensors(self.color, self.alpha)  # the tile's own checks
        if self.mask is not None:
            m = self.mask
            if not isinstance(m, Tensor) or not m.is_floating_point() or m.ndim != 3 or m.shape[0] != 1:
                got = tuple(m.shape) if isinstance(m, Tensor) else type(m).__name__
                raise LasagnaError(f"got {got}; expected a floating-point tensor (1, h, w) or None", "TileTensors.mask")


def resample_tile(tile: Tensor, scale: float) -> Tensor:
    """The tile ``(C, th, tw)`` at ``scale`` percent (module docstring, step 1), float64; itself at 100 %."""
    th, tw = tile.shape[-2:]
    size = (scaled_side(th, scale), scaled_side(tw, scale))
    tile = tile.to(torch.float64)
    if float(scale) == 100.0 or size == (th, tw):
        return tile
    return F.interpolate(tile[None], size=size, mode="bilinear", align_corners=False, antialias=True)[0]


def pattern_fill(
    color: Tensor,
    alpha: Tensor | None,
    scale: float,
    phase: Sequence[int],
    anchor: Box,
    viewport: Box,
    dtype: torch.dtype | None = None,
) -> tuple[Tensor, Tensor | None]:
    """A pattern fill's colour ``(C, h, w)`` and alpha ``(1, h, w)`` (None: an opaque tile) on ``viewport``, the
    tile ``color (C, th, tw)`` / ``alpha (1, th, tw)`` repeated from ``anchor``'s corner plus ``phase`` (both boxes
    (x0, y0, x1, y1) in canvas pixels; module docstring)."""
    dtype = dtype or torch.get_default_dtype()
    if color.ndim != 3 or (alpha is not None and (alpha.ndim != 3 or alpha.shape[-2:] != color.shape[-2:])):
        got = f"{tuple(color.shape)}" + ("" if alpha is None else f" and alpha {tuple(alpha.shape)}")
        raise LasagnaError(f"tile is {got}; expected (C, th, tw) and alpha (1, th, tw)", "pattern.source")
    if not float(scale) > 0.0:
        raise LasagnaError(f"is {scale}; expected a scale above 0 percent", "pattern.scale")
    problem = tile_problem(color.shape[-2], color.shape[-1], scale)
    if problem is not None:
        raise LasagnaError(problem, "pattern.source")
    tile = color if alpha is None else torch.cat([color.to(alpha.dtype), alpha])
    tile = resample_tile(tile, scale)
    th, tw = tile.shape[-2:]
    ox, oy = anchor[0] + int(phase[0]), anchor[1] + int(phase[1])
    rows = torch.remainder(torch.arange(viewport[1] - oy, viewport[3] - oy, device=tile.device), th)
    cols = torch.remainder(torch.arange(viewport[0] - ox, viewport[2] - ox, device=tile.device), tw)
    out = tile.index_select(-2, rows).index_select(-1, cols).to(dtype)  # (C (+1), h, w)
    if alpha is None:
        return out, None
    return out[:-1], out[-1:]


__all__ = ["TileTensors", "pattern_fill", "resample_tile"]
