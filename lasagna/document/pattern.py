"""Pattern fills: how a pattern layer's tile is laid over its rectangle (Photoshop's pattern fill layer).

The tile is the layer's ``source`` PNG (RGB or RGBA, 8 or 16 bits); this record holds the dialog's numbers: the
scale in percent (the tile is resampled to ⌊scale/100 · side⌋ pixels a side, as psd-tools does), the phase (the
tiling's origin moved by whole pixels, +y down) and ``align`` (the tiling starts at the layer's rectangle, or at the
canvas's corner). ``lasagna.compose.pattern`` renders it.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, Strict

from lasagna.document.types import StrictModel
from lasagna.limits import MAX_PATTERN_PIXELS

# Photoshop's pattern dialog scales 1…1000 %; 0 % would be a tile of no pixels.
SCALE_MIN, SCALE_MAX = 1.0, 1000.0
# A phase is taken modulo the tile's side; a canvas side (32768) either way is every phase there is.
PHASE_LIMIT = 32768
Phase = Annotated[int, Strict(), Field(ge=-PHASE_LIMIT, le=PHASE_LIMIT)]


class PatternFill(StrictModel):
    """A pattern fill's tiling (Photoshop's Pattern Fill dialog; ``lasagna.compose.pattern`` renders it)."""

    scale: float = Field(
        100.0,
        ge=SCALE_MIN,
        le=SCALE_MAX,
        strict=True,
        allow_inf_nan=False,
        description="Percent, 1…1000: the tile is resampled (bilinear) to ⌊scale/100 · side⌋ pixels a side.",
    )
    phase: tuple[Phase, Phase] = Field(
        (0, 0),
        description="The tiling's origin moved by [x, y] whole pixels (+y down), each −32768…32768.",
    )
    align: bool = Field(
        True,
        strict=True,
        description="Align with layer: the tiling starts at the layer's rectangle (true) or the canvas's corner "
        "(false).",
    )


def scaled_side(side: int, scale: float) -> int:
    """A tile side at ``scale`` percent, as psd-tools sizes it: max(1, ⌊side · (scale/100)⌋)."""
    return max(1, int(side * (float(scale) / 100.0)))


def tile_problem(height: int, width: int, scale: float) -> str | None:
    """What breaks the rule "a tile, as stored and as resampled at its scale, holds at most ``MAX_PATTERN_PIXELS``
    pixels", or None."""
    for what, h, w in (
        ("tile", height, width),
        (f"tile at {scale:g} %", scaled_side(height, scale), scaled_side(width, scale)),
    ):
        if h * w > MAX_PATTERN_PIXELS:
            return f"{what} is {w}x{h} ({w * h} pixels); expected at most {MAX_PATTERN_PIXELS} pixels"
    return None
