"""PSD adjustment and fill records (as psd-tools reads them) → the document's parameters, for ``import-psd``.

The tone adjustments psd-tools composites (levels, curves, …) are read in ``psd_import.adjustment_params``; this
module reads the others — channel mixer, color balance, vibrance, black & white, gradient map, photo filter, and
hue/saturation's colour ranges — and fill layers' settings (solid colour, gradient). Units follow the PSD records
(Adobe's "Photoshop File Formats Specification", "Adjustment layers" and "Color structure"): colours are 16-bit
components of a colour space (0 RGB, 1 HSB, 7 Lab, 8 gray), slider values are Photoshop's dialog numbers, gradient
locations are 0…4096 and midpoints percent. What a record holds that a stack cannot is one warning line.
"""

from __future__ import annotations

import colorsys
import struct
from collections.abc import Callable
from typing import Any

Warn = Callable[[str], None]


def _unit(v: float) -> float:
    return min(max(float(v), 0.0), 1.0)


def _lab_to_rgb(L: float, a: float, b: float) -> tuple[float, float, float]:
    """CIE Lab (D50, Photoshop's colour pickers' reference white) → sRGB in [0, 1] (clipped): Lab → XYZ D50, the
    Bradford adaptation to D65, the sRGB matrix and transfer function (IEC 61966-2-1)."""
    fy = (L + 16.0) / 116.0
    fx, fz = fy + a / 500.0, fy - b / 200.0

    def finv(t: float) -> float:
        return t**3 if t**3 > 216.0 / 24389.0 else (116.0 * t - 16.0) * 27.0 / 24389.0

    X, Y, Z = 0.96422 * finv(fx), finv(fy), 0.82521 * finv(fz)
    Xd = 0.9555766 * X - 0.0230393 * Y + 0.0631636 * Z  # Bradford D50 → D65
    Yd = -0.0282895 * X + 1.0099416 * Y + 0.0210077 * Z
    Zd = 0.0122982 * X - 0.0204830 * Y + 1.3299098 * Z
    lin = (
        3.2404542 * Xd - 1.5371385 * Yd - 0.4985314 * Zd,
        -0.9692660 * Xd + 1.8760108 * Yd + 0.0415560 * Zd,
        0.0556434 * Xd - 0.2040259 * Yd + 1.0572252 * Zd,
    )

    def encode(c: float) -> float:
        c = _unit(c)
        return 12.92 * c if c <= 0.0031308 else 1.055 * c ** (1 / 2.4) - 0.055

    return tuple(_unit(encode(c)) for c in lin)  # type: ignore[return-value]


def record_color(space: int, components, warn: Warn, what: str) -> tuple[float, float, float] | None:
    """A PSD colour record (space, four 16-bit components) as RGB in [0, 1], or None (with a warning line)."""
    c = [int(v) for v in components]
    if space == 0:  # RGB: full unsigned 16-bit values
        return tuple(_unit(v / 65535.0) for v in c[:3])  # type: ignore[return-value]
    if space == 1:  # HSB: hue, saturation, brightness, each 0…65535
        return colorsys.hsv_to_rgb(c[0] / 65536.0, c[1] / 65535.0, c[2] / 65535.0)
    if space == 7:  # Lab: L 0…10000, a and b signed −12800…12700
        signed = [v - 65536 if v >= 32768 else v for v in c]
        return _lab_to_rgb(signed[0] / 100.0, signed[1] / 100.0, signed[2] / 100.0)
    if space == 8:  # gray: 0…10000, 10000 black
        g = 1.0 - c[0] / 10000.0
        return (g, g, g)
    warn(f"{what}: colour space {space} cannot be read; expected RGB, HSB, Lab or gray")
    return None


def descriptor_color(desc, warn: Warn, what: str) -> tuple[float, float, float] | None:
    """An RGB colour descriptor (``RGBC``: Rd, Grn, Bl in 0…255; ``HSBC``; ``Grsc``; ``LbCl``) as RGB in [0, 1]."""
    if desc is None:
        return None
    keys = {bytes(k).strip(): v for k, v in desc.items()}
    if b"Rd" in keys:
        blue = keys.get(b"Bl", keys.get(b"Bl  "))
        return tuple(_unit(float(v) / 255.0) for v in (keys[b"Rd"], keys[b"Grn"], blue))  # type: ignore[return-value]
    if b"H" in keys:
        return colorsys.hsv_to_rgb(
            float(keys[b"H"]) / 360.0, float(keys[b"Strt"]) / 100.0, float(keys[b"Brgh"]) / 100.0
        )
    if b"Gry" in keys:
        g = 1.0 - float(keys[b"Gry"]) / 100.0
        return (g, g, g)
    if b"Lmnc" in keys:
        return _lab_to_rgb(float(keys[b"Lmnc"]), float(keys[b"A"]), float(keys[b"B"]))
    warn(f"{what}: a colour descriptor of class {desc.classID!r} cannot be read; expected RGB, HSB, gray or Lab")
    return None


def _clamp(v: float, lo: float, hi: float) -> float:
    return min(max(float(v), lo), hi)


def channel_mixer(layer, warn: Warn, what: str) -> dict | None:
    """'mixr': version, monochrome, then per output channel (red, green, blue; a fourth for CMYK) five signed shorts:
    the red, green, blue (and black) source percentages and the constant. psd-tools keeps the first five in ``data``
    and the rest as bytes."""
    raw = layer._data
    shorts = list(raw.data) + list(
        struct.unpack(f">{len(raw.unknown) // 2}h", raw.unknown[: len(raw.unknown) // 2 * 2])
    )
    if len(shorts) < 15:
        warn(f"{what}: channel mixer record holds {len(shorts)} values; expected 15 (three channels); left out")
        return None
    rows = [
        [_clamp(v, -200.0, 200.0) for v in (s[0], s[1], s[2], s[4])] for s in (shorts[0:5], shorts[5:10], shorts[10:15])
    ]
    if layer.monochrome:  # Photoshop keeps the monochrome mix in the first channel's record
        return dict(type="channel-mixer", gray=rows[0])
    return dict(type="channel-mixer", red=rows[0], green=rows[1], blue=rows[2])


def color_balance(layer, warn: Warn, what: str) -> dict:
    """'blnc': three signed shorts (cyan–red, magenta–green, yellow–blue, −100…100) per range, the luminosity flag."""

    def shift(values) -> list[float]:
        return [_clamp(v, -100.0, 100.0) for v in values]

    return dict(
        type="color-balance",
        shadows=shift(layer.shadows),
        midtones=shift(layer.midtones),
        highlights=shift(layer.highlights),
        preserve_luminosity=bool(layer.luminosity),
    )


def vibrance(layer, warn: Warn, what: str) -> dict:
    return dict(
        type="vibrance",
        vibrance=_clamp(layer.vibrance, -100.0, 100.0),
        saturation=_clamp(layer.saturation, -100.0, 100.0),
    )


def black_and_white(layer, warn: Warn, what: str) -> dict:
    out: dict[str, Any] = dict(type="black-and-white")
    for name, value in (
        ("reds", layer.red),
        ("yellows", layer.yellow),
        ("greens", layer.green),
        ("cyans", layer.cyan),
        ("blues", layer.blue),
        ("magentas", layer.magenta),
    ):
        out[name] = _clamp(value, -200.0, 300.0)
    if layer.use_tint:
        tint = descriptor_color(layer.tint_color, warn, f"{what}: tint")
        if tint is not None:
            out["tint"] = list(tint)
    return out


def gradient_stops(locations, midpoints, values, key: str = "color") -> list[dict]:
    """Stops as the document's (``key``: "color" for colour stops, "opacity" for opacity stops): a PSD stop's
    midpoint (percent) is of the segment that ends at it, the document's of the one that starts at it; a location
    before the previous stop's is read as that one's (the order is kept)."""
    stops: list[dict] = []
    for i, (loc, value) in enumerate(zip(locations, values)):
        if stops:
            stops[-1]["midpoint"] = _clamp(midpoints[i] / 100.0, 0.05, 0.95)
        value = list(value) if key == "color" else _unit(value)
        stops.append({"location": max(_unit(loc), stops[-1]["location"] if stops else 0.0), key: value})
        stops[-1]["midpoint"] = 0.5
    if len(stops) == 1:
        stops = [{**stops[0], "location": 0.0}, {**stops[0], "location": 1.0}]
    return stops


def gradient_map(layer, warn: Warn, what: str) -> dict | None:
    """'grdm': colour stops (location 0…4096, midpoint percent, a colour record), transparency stops, smoothness."""
    colors, locations, midpoints = [], [], []
    for stop in layer.color_stops or []:
        rgb = record_color(stop.mode, stop.color, warn, f"{what}: gradient stop")
        if rgb is None:
            return None
        colors.append(rgb)
        locations.append(stop.location / 4096.0)
        midpoints.append(stop.midpoint)
    if not colors:
        warn(f"{what}: gradient map has no colour stops; left out")
        return None
    if any(t.opacity < 100 for t in layer.transparency_stops or []):
        warn(f"{what}: a gradient map's transparency stops cannot be represented; read as opaque")
    if layer.interpolation:
        warn(
            f"{what}: gradient smoothness {round(layer.interpolation * 100)} % read as 0 % (colours mix linearly "
            "between stops)"
        )
    return dict(type="gradient-map", stops=gradient_stops(locations, midpoints, colors), reverse=bool(layer.reversed))


# Photoshop's gradient fill styles (the descriptor's 'Type' enum) → the document's.
GRADIENT_STYLES = {b"Lnr ": "linear", b"Rdl ": "radial", b"Angl": "angle", b"Rflc": "reflected", b"Dmnd": "diamond"}


def _value(desc, key: bytes, default: Any = None) -> Any:
    v = desc.get(key, default) if desc is not None else default
    return getattr(v, "value", v)


def gradient_fill(desc, warn: Warn, what: str) -> dict | None:
    """A gradient fill layer's 'GdFl' descriptor (Type, Angl, Scl, Rvrs, Algn, Ofst {Hrzn, Vrtc} percent, Grad:
    GrdF custom stops, Clrs [Clr, Lctn 0…4096, Mdpn percent], Trns [Opct percent, Lctn, Mdpn], Intr smoothness)
    as the document's ``gradient``, or None (a noise gradient; read as its stored pixels, with a warning)."""
    grad = desc.get(b"Grad")
    style = GRADIENT_STYLES.get(bytes(getattr(desc.get(b"Type"), "enum", b"") or b""))
    form = bytes(getattr(grad.get(b"GrdF"), "enum", b"CstS") or b"") if grad is not None else b""
    if grad is None or style is None or form != b"CstS":
        why = "a noise gradient" if style is not None and grad is not None else "a gradient style a stack lacks"
        warn(f"{what}: {why} cannot be represented as a gradient layer; the fill's pixels are imported")
        return None
    colors, locations, midpoints = [], [], []
    for stop in grad.get(b"Clrs", []):
        rgb = descriptor_color(stop.get(b"Clr "), warn, f"{what}: gradient stop")
        if rgb is None:
            return None
        colors.append(rgb)
        locations.append(float(_value(stop, b"Lctn", 0)) / 4096.0)
        midpoints.append(float(_value(stop, b"Mdpn", 50)))
    if not colors:
        warn(f"{what}: gradient fill has no colour stops; its pixels kept")
        return None
    out: dict[str, Any] = dict(
        style=style,
        angle=_clamp(_value(desc, b"Angl", 90.0), -360.0, 360.0),
        scale=_clamp(_value(desc, b"Scl ", 100.0), 10.0, 1000.0),
        reverse=bool(_value(desc, b"Rvrs", False)),
        align=bool(_value(desc, b"Algn", True)),
        stops=gradient_stops(locations, midpoints, colors),
    )
    offset = desc.get(b"Ofst")
    if offset is not None:
        out["shift"] = [_clamp(_value(offset, k, 0.0), -1000.0, 1000.0) for k in (b"Hrzn", b"Vrtc")]
    alphas = [
        (float(_value(t, b"Lctn", 0)) / 4096.0, float(_value(t, b"Mdpn", 50)), float(_value(t, b"Opct", 100.0)) / 100.0)
        for t in grad.get(b"Trns", [])
    ]
    if alphas and any(a < 1.0 for _, _, a in alphas):
        out["opacity_stops"] = gradient_stops(*zip(*alphas), key="opacity")
    smooth = float(_value(grad, b"Intr", 0.0))
    if smooth:
        warn(
            f"{what}: gradient smoothness {round(smooth / 40.96)} % read as 0 % (colours mix linearly between stops, "
            "as psd-tools renders)"
        )
    return out


def pattern_fill(desc, warn: Warn, what: str) -> tuple[str, dict] | None:
    """A pattern fill layer's 'PtFl' descriptor (Ptrn {Nm, Idnt}, Scl percent, Algn, phase {Hrzn, Vrtc} pixels, Angl)
    as (the pattern's id, the document's ``pattern``), or None (a scale outside 1…1000 %; its pixels are read, with a
    warning). A phase is rounded to whole pixels and an angle read as 0° (psd-tools renders neither), each warned."""
    ref = desc.get(b"Ptrn")
    ident = str(_value(ref, b"Idnt", "") or "").rstrip("\x00")
    if not ident:
        warn(f"{what}: pattern fill names no pattern; the fill's pixels are imported")
        return None
    scale = float(_value(desc, b"Scl ", 100.0))
    if not 1.0 <= scale <= 1000.0:
        warn(f"{what}: pattern scale {scale:g} % is outside 1…1000 %; the fill's pixels are imported")
        return None
    phase_desc = desc.get(b"phase")
    raw = [float(_value(phase_desc, k, 0.0)) for k in (b"Hrzn", b"Vrtc")]
    phase = [int(round(v)) for v in raw]
    if any(abs(v) > 32768 for v in phase):
        warn(f"{what}: pattern phase {raw} is beyond ±32768 pixels; the fill's pixels are imported")
        return None
    if raw != [float(v) for v in phase]:
        warn(f"{what}: pattern phase {raw} rounded to whole pixels {phase}")
    angle = float(_value(desc, b"Angl", 0.0))
    if angle % 360.0:
        warn(f"{what}: pattern angle {angle:g}° read as 0° (the tile is not rotated, as psd-tools renders)")
    return ident, dict(scale=scale, phase=phase, align=bool(_value(desc, b"Algn", True)))


def photo_filter(layer, warn: Warn, what: str) -> dict | None:
    """'phfl': version 2 holds a colour record, version 3 three 32-bit Lab values (read ×1/100, as ag-psd reads them:
    unverified against Photoshop), then density (percent) and the luminosity flag."""
    if layer.xyz is not None:
        L, a, b = (v - 2**32 if v >= 2**31 else v for v in layer.xyz)
        rgb = _lab_to_rgb(L / 100.0, a / 100.0, b / 100.0)
        warn(f"{what}: photo filter colour of a version 3 record read as Lab/100 (unverified against Photoshop)")
    else:
        rgb = record_color(layer.color_space, layer.color_components, warn, f"{what}: photo filter")
        if rgb is None:
            return None
    return dict(
        type="photo-filter",
        color=list(rgb),
        density=_clamp(layer.density or 0, 0.0, 100.0),
        preserve_luminosity=bool(layer.luminosity),
    )


def hue_ranges(items) -> list[dict]:
    """Hue/saturation's six colour-range records ([begin, full_begin, full_end, end] degrees, (hue, saturation,
    lightness)) as the document's ``ranges``, those that change nothing left out."""
    out = []
    for corners, (h, s, light) in items or []:
        if (h, s, light) == (0, 0, 0):
            continue
        out.append(
            dict(
                range=[_clamp(c, -360.0, 720.0) for c in corners],
                hue=_clamp(h, -180.0, 180.0),
                saturation=_clamp(s, -100.0, 100.0),
                lightness=_clamp(light, -100.0, 100.0),
            )
        )
    return out


# psd-tools' layer kind → reader of the document's adjustment parameters (the kinds psd_import does not read itself).
READERS: dict[str, Callable[[Any, Warn, str], dict | None]] = {
    "channelmixer": channel_mixer,
    "colorbalance": color_balance,
    "vibrance": vibrance,
    "blackandwhite": black_and_white,
    "gradientmap": gradient_map,
    "photofilter": photo_filter,
}
