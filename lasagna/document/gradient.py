"""Gradients: colour and opacity stops, and a gradient fill's ramp (Photoshop's gradient fill layer).

A gradient is read at a position t ∈ [0, 1]. Stops are in the document's units, not the PSD's: ``location`` in
[0, 1] (a PSD stores 0…4096: location/4096), colours RGB in [0, 1], opacity in [0, 1] (a PSD's percent/100), and a
stop's ``midpoint`` is of the segment that *starts* at it (a PSD stores it on the stop that ends the segment). The
ramp's parameters are Photoshop's dialog's: style, angle in degrees, scale in percent, reverse, align with layer,
and the offset (``shift``) in percent of the anchor box. ``lasagna.compose.gradient`` renders them.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import AllowInfNan, Field, Strict, model_validator

from lasagna.document.types import OpaqueColour, StrictModel, Unit
from lasagna.document.validation import RuleError
from lasagna.limits import MAX_GRADIENT_STOPS

# Photoshop's five gradient fill styles (its "Shape Burst" exists only in a stroke effect).
GRADIENT_STYLES = ("linear", "radial", "angle", "reflected", "diamond")
# Bounds of the ramp's numbers: an angle of one turn either way; Photoshop's dialog scales 10…150 % (newer versions
# up to 1000 %, kept for other writers); an offset a few boxes away is already off the ramp's ends.
ANGLE_LIMIT = 360.0
SCALE_MIN, SCALE_MAX = 10.0, 1000.0
SHIFT_LIMIT = 1000.0
Percent = Annotated[float, Strict(), AllowInfNan(False), Field(ge=-SHIFT_LIMIT, le=SHIFT_LIMIT)]

Midpoint = Annotated[
    float,
    Field(
        0.5,
        ge=0.05,
        le=0.95,
        strict=True,
        allow_inf_nan=False,
        description="Where, between this stop and the next (fraction of the way), the value is half of each: "
        "0.05…0.95 (Photoshop's 5…95 %).",
    ),
]


class GradientStop(StrictModel):
    """A colour stop of a gradient: where it is, its colour, and where the blend to the next stop is half-way."""

    location: Unit = Field(description="Position in [0, 1].")
    color: OpaqueColour = Field(description="RGB in [0, 1].")
    midpoint: Midpoint


class OpacityStop(StrictModel):
    """An opacity (transparency) stop of a gradient: where it is, its opacity, and its midpoint to the next."""

    location: Unit = Field(description="Position in [0, 1].")
    opacity: Unit = Field(description="Opacity in [0, 1] (a PSD's percent / 100).")
    midpoint: Midpoint


def check_stops(stops: tuple[GradientStop | OpacityStop, ...] | None, name: str) -> None:
    """Rule: stops are listed in increasing location (two stops may share one: a hard edge)."""
    if stops is None:
        return
    xs = [s.location for s in stops]
    if any(b < a for a, b in zip(xs, xs[1:])):
        raise RuleError(f"{name} locations {xs} are not sorted; expected stops in increasing location", loc=(name,))


STOPS = dict(min_length=2, max_length=MAX_GRADIENT_STOPS)


class GradientFill(StrictModel):
    """A gradient fill's ramp and stops (Photoshop's Gradient Fill dialog; ``lasagna.compose.gradient`` renders it)."""

    style: Literal["linear", "radial", "angle", "reflected", "diamond"] = Field(
        "linear", description="Ramp style: linear, radial, angle, reflected or diamond (Photoshop's five)."
    )
    angle: float = Field(
        90.0,
        ge=-ANGLE_LIMIT,
        le=ANGLE_LIMIT,
        strict=True,
        allow_inf_nan=False,
        description="Degrees, counter-clockwise from the +x axis (90: t runs bottom to top), −360…360.",
    )
    scale: float = Field(
        100.0,
        ge=SCALE_MIN,
        le=SCALE_MAX,
        strict=True,
        allow_inf_nan=False,
        description="Percent, 10…1000: the ramp's length relative to the anchor box.",
    )
    reverse: bool = Field(False, strict=True, description="Run the gradient from its last stop to its first.")
    align: bool = Field(
        True,
        strict=True,
        description="Align with layer: the ramp spans the layer's rectangle (true) or the canvas (false).",
    )
    shift: tuple[Percent, Percent] = Field(
        (0.0, 0.0),
        description="Photoshop's offset: the ramp's centre moved by [x, y] percent of the anchor box (+y down), "
        "each −1000…1000.",
    )
    stops: tuple[GradientStop, ...] = Field(
        **STOPS, description=f"Colour stops, 2 to {MAX_GRADIENT_STOPS}, in increasing location."
    )
    opacity_stops: tuple[OpacityStop, ...] | None = Field(
        None,
        **STOPS,
        description=f"Opacity stops, 2 to {MAX_GRADIENT_STOPS}, in increasing location; null: opaque everywhere.",
    )

    @model_validator(mode="after")
    def _valid(self) -> GradientFill:
        check_stops(self.stops, "stops")
        check_stops(self.opacity_stops, "opacity_stops")
        return self
