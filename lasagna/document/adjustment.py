"""The parameters of an adjustment layer: one strict model per adjustment, gathered in the union ``Adjustment``.

An adjustment layer (``kind: "adjustment"``, ``lasagna.document.models.AdjustmentLayer``) applies a parametric
function to what lies below it, as Photoshop's adjustment layers do; the function is ``lasagna.compose.adjust``'s
of the same ``type``. Units: colour values, levels and curve points are the document's colour unit [0, 1] (a
Photoshop code / 255); strengths are Photoshop's dialog units (brightness −150…150, hue degrees, saturation and
lightness percent, exposure stops), so a number read off Photoshop's panel is the number written here.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field, StrictInt, model_validator

from lasagna.document.gradient import STOPS, GradientStop, check_stops
from lasagna.document.types import FiniteFloat, OpaqueColour, StrictModel, Unit
from lasagna.document.validation import RuleError
from lasagna.limits import MAX_CURVE_POINTS, MAX_GRADIENT_STOPS

# Photoshop's levels and exposure dialogs take a gamma in [0.01, 9.99] (psd-tools clamps a stored one there).
GAMMA_MIN, GAMMA_MAX = 0.01, 9.99
Gamma = Annotated[float, Field(ge=GAMMA_MIN, le=GAMMA_MAX, strict=True, allow_inf_nan=False)]


class LevelsChannel(StrictModel):
    """One channel's levels: input black/white points, midtone gamma, output black/white points."""

    in_black: Unit = Field(0.0, description="Input black point in [0, 1]: values at or below it map to out_black.")
    in_white: Unit = Field(1.0, description="Input white point in [0, 1]: values at or above it map to out_white.")
    gamma: Gamma = Field(1.0, description="Midtone gamma in [0.01, 9.99]: t ↦ t^(1/gamma) between the points.")
    out_black: Unit = Field(0.0, description="Output black point in [0, 1].")
    out_white: Unit = Field(1.0, description="Output white point in [0, 1].")

    @model_validator(mode="after")
    def _input_points_ordered(self) -> LevelsChannel:
        if self.in_black >= self.in_white:
            raise RuleError(
                f"in_black {self.in_black} is not below in_white {self.in_white}; expected in_black < in_white",
                loc=("in_white",),
            )
        return self


_IDENTITY_LEVELS = LevelsChannel()


class Levels(StrictModel):
    """Levels: each of red, green, blue by its own channel's levels, then all three by ``rgb`` (Photoshop's order)."""

    type: Literal["levels"] = Field("levels", description="Adjustment: levels.")
    rgb: LevelsChannel = Field(_IDENTITY_LEVELS, description="The composite channel's levels, applied last.")
    red: LevelsChannel = Field(_IDENTITY_LEVELS, description="The red channel's levels.")
    green: LevelsChannel = Field(_IDENTITY_LEVELS, description="The green channel's levels.")
    blue: LevelsChannel = Field(_IDENTITY_LEVELS, description="The blue channel's levels.")


CurvePoint = tuple[Unit, Unit]


def _check_curve(points: tuple[CurvePoint, ...] | None, name: str) -> None:
    if points is None:
        return
    xs = [p[0] for p in points]
    if any(b <= a for a, b in zip(xs, xs[1:])):
        raise RuleError(
            f"{name} inputs {xs} are not strictly increasing; expected points [x, y] sorted by x, each x once",
            loc=(name,),
        )


_CURVE = dict(min_length=2, max_length=MAX_CURVE_POINTS)


class Curves(StrictModel):
    """Curves: a natural cubic spline through each curve's points (flat beyond its end points), each of red,
    green, blue by its own curve, then all three by ``rgb``. A curve left out (null) is the identity."""

    type: Literal["curves"] = Field("curves", description="Adjustment: curves.")
    rgb: tuple[CurvePoint, ...] | None = Field(
        None, **_CURVE, description=f"The composite channel's points [x, y] in [0, 1], 2 to {MAX_CURVE_POINTS}."
    )
    red: tuple[CurvePoint, ...] | None = Field(None, **_CURVE, description="The red channel's points.")
    green: tuple[CurvePoint, ...] | None = Field(None, **_CURVE, description="The green channel's points.")
    blue: tuple[CurvePoint, ...] | None = Field(None, **_CURVE, description="The blue channel's points.")

    @model_validator(mode="after")
    def _sorted(self) -> Curves:
        for name in ("rgb", "red", "green", "blue"):
            _check_curve(getattr(self, name), name)
        return self


class Colorize(StrictModel):
    """Hue/saturation's colorize: every pixel takes this hue and saturation, its lightness shifted."""

    hue: float = Field(0.0, ge=0.0, le=360.0, strict=True, allow_inf_nan=False, description="Hue in degrees.")
    saturation: float = Field(
        25.0, ge=0.0, le=100.0, strict=True, allow_inf_nan=False, description="Saturation in percent."
    )
    lightness: float = Field(
        0.0, ge=-100.0, le=100.0, strict=True, allow_inf_nan=False, description="Lightness shift in percent."
    )


HueDegrees = Annotated[float, Field(ge=-360.0, le=720.0, strict=True, allow_inf_nan=False)]


class HueRange(StrictModel):
    """One of hue/saturation's colour ranges (Photoshop's Reds, Yellows, … entries): a shift that applies to the
    hues inside a trapezoid on the hue circle, fully between its inner points, fading to 0 at its outer ones."""

    range: tuple[HueDegrees, HueDegrees, HueDegrees, HueDegrees] = Field(
        description="[begin, full_begin, full_end, end] hue in degrees, counter-clockwise, read modulo 360 (the "
        "reds' default is [315, 345, 15, 45])."
    )
    hue: float = Field(0.0, ge=-180.0, le=180.0, strict=True, allow_inf_nan=False, description="Hue shift, degrees.")
    saturation: float = Field(
        0.0, ge=-100.0, le=100.0, strict=True, allow_inf_nan=False, description="Saturation change in percent."
    )
    lightness: float = Field(
        0.0, ge=-100.0, le=100.0, strict=True, allow_inf_nan=False, description="Lightness change in percent."
    )


class HueSaturation(StrictModel):
    """Hue/saturation: the master channel's lightness towards white or black, then hue rotated and saturation
    scaled in HSL, with the colour ranges' shifts where a pixel's hue lies in them; with ``colorize`` every pixel
    takes its hue and saturation instead."""

    type: Literal["hue-saturation"] = Field("hue-saturation", description="Adjustment: hue/saturation.")
    hue: float = Field(0.0, ge=-180.0, le=180.0, strict=True, allow_inf_nan=False, description="Hue shift, degrees.")
    saturation: float = Field(
        0.0, ge=-100.0, le=100.0, strict=True, allow_inf_nan=False, description="Saturation change in percent."
    )
    lightness: float = Field(
        0.0, ge=-100.0, le=100.0, strict=True, allow_inf_nan=False, description="Lightness change in percent."
    )
    colorize: Colorize | None = Field(None, description="If set, colorize (hue, saturation, lightness) instead.")
    ranges: tuple[HueRange, ...] = Field(
        (), max_length=6, description="Up to six colour ranges, applied in order after the master channel."
    )


class BrightnessContrast(StrictModel):
    """Brightness/contrast: Photoshop's (a curve through the brightness and contrast controls) or, with
    ``legacy``, the pre-CS3 one (a linear shift, then a linear stretch about mid-gray)."""

    type: Literal["brightness-contrast"] = Field("brightness-contrast", description="Adjustment: brightness/contrast.")
    brightness: float = Field(
        0.0, ge=-150.0, le=150.0, strict=True, allow_inf_nan=False, description="Brightness, −150…150 (legacy ±100)."
    )
    contrast: float = Field(
        0.0, ge=-100.0, le=100.0, strict=True, allow_inf_nan=False, description="Contrast, −50…100 (legacy ±100)."
    )
    legacy: bool = Field(False, strict=True, description="Photoshop's legacy (pre-CS3) algorithm.")

    @model_validator(mode="after")
    def _in_photoshops_ranges(self) -> BrightnessContrast:
        b, c = (100.0, (-100.0, 100.0)) if self.legacy else (150.0, (-50.0, 100.0))
        if abs(self.brightness) > b:
            raise RuleError(
                f"brightness {self.brightness} with legacy {self.legacy}; expected within ±{b}", ("brightness",)
            )
        if not c[0] <= self.contrast <= c[1]:
            raise RuleError(
                f"contrast {self.contrast} with legacy {self.legacy}; expected within [{c[0]}, {c[1]}]", ("contrast",)
            )
        return self


class Exposure(StrictModel):
    """Exposure: in linear light (a 2.2 power), scaled by 2^exposure and offset, then the gamma."""

    type: Literal["exposure"] = Field("exposure", description="Adjustment: exposure.")
    exposure: float = Field(0.0, ge=-20.0, le=20.0, strict=True, allow_inf_nan=False, description="Stops, −20…20.")
    offset: float = Field(0.0, ge=-0.5, le=0.5, strict=True, allow_inf_nan=False, description="Offset, −0.5…0.5.")
    gamma: Gamma = Field(1.0, description="Gamma correction in [0.01, 9.99].")


class Invert(StrictModel):
    """Invert: 1 − C."""

    type: Literal["invert"] = Field("invert", description="Adjustment: invert.")


class Posterize(StrictModel):
    """Posterize: each channel to ``levels`` evenly spaced values. Photoshop bins a document's integer codes, bin
    k holding the codes c with floor(c·levels / 2^bits) = k, so the bins depend on the document's depth."""

    type: Literal["posterize"] = Field("posterize", description="Adjustment: posterize.")
    levels: StrictInt = Field(4, ge=2, le=255, description="Values per channel, 2…255.")
    bits: Literal[8, 16] = Field(8, description="The depth whose codes are binned: 8 or 16 (Photoshop's document's).")


class Threshold(StrictModel):
    """Threshold: white where the luminosity 0.3R + 0.59G + 0.11B reaches ``level``, black elsewhere."""

    type: Literal["threshold"] = Field("threshold", description="Adjustment: threshold.")
    level: FiniteFloat = Field(
        0.5,
        gt=0.0,
        le=1.0,
        description="Threshold in (0, 1]; Photoshop's level L on b-bit codes is L/255 − ½/(2^b − 1).",
    )


def _percent(lo: float, hi: float, default: float, description: str) -> Any:
    return Field(default, ge=lo, le=hi, strict=True, allow_inf_nan=False, description=description)


MixerWeight = Annotated[float, Field(ge=-200.0, le=200.0, strict=True, allow_inf_nan=False)]
MixerRow = tuple[MixerWeight, MixerWeight, MixerWeight, MixerWeight]


class ChannelMixer(StrictModel):
    """Channel mixer: each output channel Σ (weight/100)·(R, G, B) + constant/100, clamped to [0, 1] (Photoshop's
    dialog: source channels and a constant in percent, −200…200); with ``gray`` (Photoshop's "Monochrome") every
    channel is that row's gray."""

    type: Literal["channel-mixer"] = Field("channel-mixer", description="Adjustment: channel mixer.")
    red: MixerRow = Field((100.0, 0.0, 0.0, 0.0), description="Red output: [red, green, blue, constant] percent.")
    green: MixerRow = Field((0.0, 100.0, 0.0, 0.0), description="Green output: [red, green, blue, constant] percent.")
    blue: MixerRow = Field((0.0, 0.0, 100.0, 0.0), description="Blue output: [red, green, blue, constant] percent.")
    gray: MixerRow | None = Field(
        None, description="Monochrome: every channel is this row's output (red, green, blue rows unused)."
    )


BalanceShift = Annotated[float, Field(ge=-100.0, le=100.0, strict=True, allow_inf_nan=False)]
Balance = tuple[BalanceShift, BalanceShift, BalanceShift]


class ColorBalance(StrictModel):
    """Color balance: a shift along cyan–red, magenta–green and yellow–blue (−100…100 each) in each of the
    shadows, midtones and highlights, weighted by the pixel's HSL lightness; ``preserve_luminosity`` keeps that
    lightness."""

    type: Literal["color-balance"] = Field("color-balance", description="Adjustment: color balance.")
    shadows: Balance = Field((0.0, 0.0, 0.0), description="[cyan–red, magenta–green, yellow–blue] in the shadows.")
    midtones: Balance = Field((0.0, 0.0, 0.0), description="[cyan–red, magenta–green, yellow–blue] in the midtones.")
    highlights: Balance = Field((0.0, 0.0, 0.0), description="[cyan–red, magenta–green, yellow–blue], highlights.")
    preserve_luminosity: bool = Field(True, strict=True, description="Keep each pixel's HSL lightness.")


class Vibrance(StrictModel):
    """Vibrance: ``saturation`` as hue/saturation's, then ``vibrance`` raises (or lowers) the saturation of the
    less saturated colours most."""

    type: Literal["vibrance"] = Field("vibrance", description="Adjustment: vibrance.")
    vibrance: float = _percent(-100.0, 100.0, 0.0, "Vibrance, −100…100.")
    saturation: float = _percent(-100.0, 100.0, 0.0, "Saturation, −100…100.")


class BlackAndWhite(StrictModel):
    """Black & white: a gray from the weights of the six hue sectors (percent, −200…300, Photoshop's defaults),
    optionally tinted."""

    type: Literal["black-and-white"] = Field("black-and-white", description="Adjustment: black & white.")
    reds: float = _percent(-200.0, 300.0, 40.0, "Weight of reds, percent.")
    yellows: float = _percent(-200.0, 300.0, 60.0, "Weight of yellows, percent.")
    greens: float = _percent(-200.0, 300.0, 40.0, "Weight of greens, percent.")
    cyans: float = _percent(-200.0, 300.0, 60.0, "Weight of cyans, percent.")
    blues: float = _percent(-200.0, 300.0, 20.0, "Weight of blues, percent.")
    magentas: float = _percent(-200.0, 300.0, 80.0, "Weight of magentas, percent.")
    tint: OpaqueColour | None = Field(None, description="If set, the gray is tinted with this RGB colour.")


class GradientMap(StrictModel):
    """Gradient map: each pixel's luminosity picks a colour of the gradient."""

    type: Literal["gradient-map"] = Field("gradient-map", description="Adjustment: gradient map.")
    stops: tuple[GradientStop, ...] = Field(
        **STOPS, description=f"Colour stops, 2 to {MAX_GRADIENT_STOPS}, in increasing location."
    )
    reverse: bool = Field(False, strict=True, description="Run the gradient from its last stop to its first.")

    @model_validator(mode="after")
    def _sorted(self) -> GradientMap:
        check_stops(self.stops, "stops")
        return self


class PhotoFilter(StrictModel):
    """Photo filter: the colour seen through a filter of ``color`` at ``density``, optionally keeping luminosity."""

    type: Literal["photo-filter"] = Field("photo-filter", description="Adjustment: photo filter.")
    color: OpaqueColour = Field((0.925, 0.541, 0.0), description="The filter's RGB (default: Warming Filter (85)).")
    density: float = _percent(0.0, 100.0, 25.0, "Density in percent, 0…100.")
    preserve_luminosity: bool = Field(True, strict=True, description="Keep each pixel's luminosity.")


_ADJUSTMENTS = (
    Levels,
    Curves,
    HueSaturation,
    BrightnessContrast,
    Exposure,
    Invert,
    Posterize,
    Threshold,
    ChannelMixer,
    ColorBalance,
    Vibrance,
    BlackAndWhite,
    GradientMap,
    PhotoFilter,
)
Adjustment = Annotated[
    Levels
    | Curves
    | HueSaturation
    | BrightnessContrast
    | Exposure
    | Invert
    | Posterize
    | Threshold
    | ChannelMixer
    | ColorBalance
    | Vibrance
    | BlackAndWhite
    | GradientMap
    | PhotoFilter,
    Field(discriminator="type"),
]
ADJUSTMENT_TYPES: tuple[str, ...] = tuple(m.model_fields["type"].default for m in _ADJUSTMENTS)
