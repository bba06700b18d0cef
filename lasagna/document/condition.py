"""Light-direction conditions as text: the eight named lights and ``az=…,el=…`` (no torch, no vectors).

A surface layer's light may also be a **point light** ``x=…,y=…,z=…`` (`parse_point`): a position over its
normal map, x and y fractions of the layer's width and height from its top-left corner (x right, y down, as a
canvas offset; 0.5, 0.5 is the layer's centre), z its height above the image plane in units of the layer's
longer side. Only a surface layer, rendered from its stored normals, can be lit by one; a learned edit's
condition is a direction, which its prior was trained on. A point light with ``cone=C`` is a **spot light**
(Lighting Effects' Spot, Blender's Spot): it shines only within C degrees (its cone's half-angle, in (0, 90]) of
its axis, from the light toward the aim point ``ax=…,ay=…`` on the layer (fractions as x and y; by default the
point beneath it), its edge softened over the fraction ``blend`` of the cone (in [0, 1], default `SPOT_BLEND`,
Blender's default; 0 is a hard edge): ``x=0.2,y=0.3,z=0.4,cone=25,ax=0.5,ay=0.6``.

A condition names a directional light either by one of the eight labels of
`lasagna.world.lighting` or by its angles in degrees, ``az=135,el=40`` (or ``el=40,az=135``):

- azimuth ``az``: the angle of the light's in-image-plane part, measured from +x (right)
  counter-clockwise toward +y (up): right = 0°, top = 90°, left = 180°, bottom = 270°. Any real
  number is accepted and wrapped to [0, 360).
- elevation ``el``: the angle between the light and the view axis +z (toward the viewer), in
  [0, 90): 0 is a light straight from the camera, 90 (grazing, excluded) would light the wall not at all.
  The eight named lights all have el = 60.

The unit vector of (az, el) is (sin el·cos az, sin el·sin az, cos el) in the camera frame (x right,
y up, z toward the viewer); it lives in `lasagna.world.lighting` (``direction_vector``), which holds
the normative text. This module only parses and formats, so the CLI and ``lasagna edit`` can read a
condition without importing torch.
"""

from __future__ import annotations

import math
import re
from typing import NamedTuple

from lasagna.errors import ConditionError

NAMED_ELEVATION = 60.0
"""Elevation (degrees from +z) of every named light."""

NAMED_DIRECTIONS: dict[str, tuple[float, float]] = {
    "left": (180.0, NAMED_ELEVATION),
    "right": (0.0, NAMED_ELEVATION),
    "top": (90.0, NAMED_ELEVATION),
    "bottom": (270.0, NAMED_ELEVATION),
    "top-left": (135.0, NAMED_ELEVATION),
    "top-right": (45.0, NAMED_ELEVATION),
    "bottom-left": (225.0, NAMED_ELEVATION),
    "bottom-right": (315.0, NAMED_ELEVATION),
}
"""(az, el) in degrees of each named light: the one list of them (its order is `lasagna.world.lighting.VOCABULARY`,
its vectors `LIGHTS`; the editor gets them from ``/api/state``)."""

AMBIENT = 0.25
"""Default ambient term a of shading = a + (1 − a)·max(0, n·l) (the world's contract)."""
DEFAULT_SHININESS = 32.0
"""A surface layer's highlight exponent p (Blinn–Phong, `lasagna.compose.surface`) when it names none: the highlight
falls to half its peak where the normal is 12° off the half vector (0.5^(1/32) = cos 12°)."""
MAX_SHININESS = 1024.0
"""The largest highlight exponent: at 1024 the highlight is 2° wide at half its peak, under a 16-bit map's steps."""

MAX_ELEVATION = 90.0
"""Elevations lie in [0, MAX_ELEVATION): at 90° the light grazes the image plane."""

_NUMBER = r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"
_PAIR = re.compile(rf"\s*(az|el)\s*=\s*({_NUMBER})\s*")
DIRECTION_PATTERN = (
    "^(?:"
    + "|".join(re.escape(n) for n in NAMED_DIRECTIONS)
    + rf"|\s*(?:az|el)\s*=\s*{_NUMBER}\s*,\s*(?:az|el)\s*=\s*{_NUMBER}\s*)$"
)
"""What JSON Schema can say of a light's text: a named light or two ``key=number`` pairs (ECMA-262 regex).
Which keys (az and el once each) and the elevation's range are checked by `parse_direction`."""
MAX_POINT_OFFSET = 16.0
"""A point light's x and y lie in [−MAX_POINT_OFFSET, 1 + MAX_POINT_OFFSET] (fractions of the layer): farther
out it lights the layer as a directional light would."""
MIN_POINT_HEIGHT = 1e-3
MAX_POINT_HEIGHT = 64.0
"""A point light's height z lies in [MIN_POINT_HEIGHT, MAX_POINT_HEIGHT] (units of the layer's longer side): a
thousandth of the layer is below a pixel of any layer we read, and a lower z would let the distance to a pixel
directly beneath the light underflow (z² < 1e-308: 0/0)."""
MAX_SPOT_CONE = 90.0
"""A spot light's cone half-angle lies in (0, MAX_SPOT_CONE] degrees: at 90° it lights the whole half-space below
it, as a point light does."""
SPOT_BLEND = 0.15
"""A spot light's default softness: the fraction of its cone (in cos θ, as Blender's ``spot_blend``) over which its
edge fades in."""
_POINT_KEYS = ("x", "y", "z", "cone", "ax", "ay", "blend")
_POINT_PAIR = re.compile(rf"\s*({'|'.join(_POINT_KEYS)})\s*=\s*({_NUMBER})\s*")
_POINT_KEY = f"(?:{'|'.join(_POINT_KEYS)})"
POINT_PATTERN = rf"^\s*{_POINT_KEY}\s*=\s*{_NUMBER}\s*(?:,\s*{_POINT_KEY}\s*=\s*{_NUMBER}\s*){{2,6}}$"
"""What JSON Schema can say of a point or spot light's text: three to seven ``key=number`` pairs of x, y, z, cone,
ax, ay and blend (ECMA-262 regex); which keys, each once, and the ranges are checked by `parse_point`."""
_EXPECTED_POINT = (
    "expected a point light 'x=X,y=Y,z=Z' (x, y: fractions of the layer's width and height from its top-left, "
    f"in [{-MAX_POINT_OFFSET:g}, {1 + MAX_POINT_OFFSET:g}]; z: height in units of its longer side, in "
    f"[{MIN_POINT_HEIGHT:g}, {MAX_POINT_HEIGHT:g}]), or a spot light adding 'cone=C' (half-angle in degrees, "
    f"in (0, {MAX_SPOT_CONE:g}]) and optionally 'ax=X,ay=Y' (where it aims, as x and y) and 'blend=B' (its edge's "
    "softness, in [0, 1])"
)


class PointLight(NamedTuple):
    """A point light (x, y, z) — or, with a ``cone``, a spot light aimed at (``ax``, ``ay``) with edge softness
    ``blend`` — in the module docstring's units."""

    x: float
    y: float
    z: float
    cone: float | None = None
    ax: float | None = None
    ay: float | None = None
    blend: float = SPOT_BLEND


_EXPECTED = (
    f"expected one of {', '.join(NAMED_DIRECTIONS)} or 'az=A,el=E' in degrees "
    f"(azimuth from +x toward +y, elevation from the view axis in [0, {MAX_ELEVATION:g}))"
)


def _bad(text: object, why: str = "") -> ConditionError:
    return ConditionError(f"{_EXPECTED}, got {text!r}{why}", where="condition")


def wrap_azimuth(az: float) -> float:
    """``az`` wrapped to [0, 360) (fmod is exact; a tiny negative that rounds up to 360 becomes 0)."""
    a = math.fmod(float(az), 360.0)
    if a < 0.0:
        a += 360.0
    if a >= 360.0:
        a = 0.0
    return a + 0.0  # −0.0 → 0.0


def check_direction(az: float, el: float, text: object = None) -> tuple[float, float]:
    """(az wrapped to [0, 360), el) after checking both are finite and el ∈ [0, 90)."""
    az, el = float(az), float(el)
    shown = text if text is not None else f"az={az!r},el={el!r}"
    if not (math.isfinite(az) and math.isfinite(el)):
        raise _bad(shown, " (angles must be finite)")
    if not 0.0 <= el < MAX_ELEVATION:
        raise _bad(shown, f" (el = {el:g} is outside [0, {MAX_ELEVATION:g}))")
    return wrap_azimuth(az), el + 0.0


def named_direction(label: str) -> tuple[float, float]:
    """(az, el) in degrees of a named light; `ConditionError` for any other name."""
    try:
        return NAMED_DIRECTIONS[label]
    except (KeyError, TypeError):
        raise ConditionError(
            f"unknown light label {label!r}; expected one of {', '.join(NAMED_DIRECTIONS)}", where="light"
        ) from None


def parse_direction(text: str) -> tuple[float, float]:
    """(az, el) in degrees from a named label or ``az=…,el=…`` / ``el=…,az=…`` (see the module docstring)."""
    if not isinstance(text, str):
        raise _bad(text)
    if text in NAMED_DIRECTIONS:
        return NAMED_DIRECTIONS[text]
    parts = text.split(",")
    matches = [_PAIR.fullmatch(p) for p in parts]
    if len(parts) != 2 or not all(matches):
        if all(_POINT_PAIR.fullmatch(p) for p in parts):
            raise _bad(
                text,
                " (a point light is only a surface layer's light: set it after the edit, by `lasagna light`, "
                "the editor or stack.json)",
            )
        raise _bad(text)
    values = {m.group(1): float(m.group(2)) for m in matches if m}
    if set(values) != {"az", "el"}:
        raise _bad(text, " (give az and el once each)")
    return check_direction(values["az"], values["el"], text)


def parse_point(text: object) -> PointLight | None:
    """The point (or spot) light of a text ``x=…,y=…,z=…[,cone=…[,ax=…,ay=…][,blend=…]]`` (the keys in any order;
    see the module docstring), a spot's aim defaulting to the point beneath it; None for a text that names no point
    (a direction: `parse_direction` reads it); `ConditionError` for a point light whose text is malformed or out
    of range."""
    if not isinstance(text, str) or text in NAMED_DIRECTIONS:
        return None
    parts = text.split(",")
    matches = [_POINT_PAIR.fullmatch(p) for p in parts]
    if not any(matches):
        return None
    if not all(matches):
        raise ConditionError(f"{_EXPECTED_POINT}, got {text!r}", where="light")
    keys = [m.group(1) for m in matches if m]
    values = {m.group(1): float(m.group(2)) for m in matches if m}
    if len(keys) != len(values) or not {"x", "y", "z"} <= set(values):
        raise ConditionError(f"{_EXPECTED_POINT}, got {text!r} (give x, y and z, each key once)", where="light")
    if "cone" not in values and set(values) != {"x", "y", "z"}:
        raise ConditionError(f"{_EXPECTED_POINT}, got {text!r} (ax, ay and blend belong to a spot's cone)", "light")
    if ("ax" in values) != ("ay" in values):
        raise ConditionError(f"{_EXPECTED_POINT}, got {text!r} (give ax and ay together)", where="light")
    if not all(math.isfinite(v) for v in values.values()):
        raise ConditionError(f"{_EXPECTED_POINT}, got {text!r} (numbers must be finite)", where="light")
    x, y, z = values["x"], values["y"], values["z"]
    ax, ay = values.get("ax", x), values.get("ay", y)
    cone, blend = values.get("cone"), values.get("blend", SPOT_BLEND)
    if (
        not all(-MAX_POINT_OFFSET <= v <= 1.0 + MAX_POINT_OFFSET for v in (x, y, ax, ay))
        or not MIN_POINT_HEIGHT <= z <= MAX_POINT_HEIGHT
        or (cone is not None and not 0.0 < cone <= MAX_SPOT_CONE)
        or not 0.0 <= blend <= 1.0
    ):
        raise ConditionError(f"{_EXPECTED_POINT}, got {text!r} (out of range)", where="light")
    if cone is None:
        return PointLight(x + 0.0, y + 0.0, z)
    return PointLight(x + 0.0, y + 0.0, z, cone, ax + 0.0, ay + 0.0, blend + 0.0)


def parse_surface_light(text: object) -> tuple[float, float, float] | tuple[float, float]:
    """A surface layer's light: (x, y, z) of a point light or (az, el) of a direction; `ConditionError` naming
    both forms for anything else."""
    point = parse_point(text)
    if point is not None:
        return point
    try:
        return parse_direction(text)  # type: ignore[arg-type]
    except ConditionError as exc:
        raise ConditionError(f"{exc.message}; or {_EXPECTED_POINT.removeprefix('expected ')}", where="light") from None


def point_direction(point: tuple[float, ...], w: int, h: int) -> tuple[float, float]:
    """(az, el) in degrees of the direction from the centre of a w × h layer toward the point light ``point``
    (the light a viewer's sphere shows for it; at the centre's zenith, az 0 and el 0)."""
    x, y, z = point[:3]
    long_side = float(max(w, h, 1))
    dx, dy = (x - 0.5) * w / long_side, (0.5 - y) * h / long_side
    az = wrap_azimuth(math.degrees(math.atan2(dy, dx))) if (dx or dy) else 0.0
    return az, math.degrees(math.atan2(math.hypot(dx, dy), z))


def format_point(x: float, y: float, z: float, *spot: float | None) -> str:
    """``x=…,y=…,z=…`` text that `parse_point` reads back to exactly (x, y, z) — and with a spot's (cone, ax, ay,
    blend) after them, as a `PointLight` holds them, ``…,cone=…,ax=…,ay=…,blend=…``."""
    text = f"x={_number(float(x))},y={_number(float(y))},z={_number(float(z))}"
    if spot and spot[0] is not None:
        cone, ax, ay, blend = (float(v) for v in spot)  # type: ignore[arg-type]
        text += f",cone={_number(cone)},ax={_number(ax)},ay={_number(ay)},blend={_number(blend)}"
    parse_point(text)
    return text


def _number(v: float) -> str:
    """The shortest text that parses back to ``v`` exactly (integers without a decimal point)."""
    return str(int(v)) if v.is_integer() else repr(v)


def format_direction(az: float, el: float) -> str:
    """``az=…,el=…`` text that `parse_direction` reads back to exactly the (wrapped) (az, el)."""
    az, el = check_direction(az, el)
    return f"az={_number(az)},el={_number(el)}"


def direction_label(az: float, el: float) -> str | None:
    """The named light at exactly (az, el) (az wrapped), or None."""
    key = check_direction(az, el)
    return next((name for name, d in NAMED_DIRECTIONS.items() if d == key), None)


def unit_vector(az: float, el: float) -> tuple[float, float, float]:
    """The unit light vector (sin el·cos az, sin el·sin az, cos el) of (az, el) in degrees (float64): the
    closed form of the module docstring's convention, for every tier that needs the vector."""
    az, el = check_direction(az, el)
    a, e = math.radians(az), math.radians(el)
    return (math.sin(e) * math.cos(a), math.sin(e) * math.sin(a), math.cos(e))


def mirror_direction(text: str, left_right: bool, top_bottom: bool) -> str:
    """The canonical condition of the light ``text`` in the image mirrored left-right (x → −x: az → 180° − az) and/or
    top-bottom (y → −y: az → −az); the elevation is kept."""
    az, el = parse_direction(text)
    if left_right:
        az = 180.0 - az
    if top_bottom:
        az = -az
    return canonical_condition(format_direction(wrap_azimuth(az), el))


def check_ambient(ambient: float) -> float:
    """Ambient must lie in [0, 1): at 1 the light would have no effect."""
    if not (0.0 <= ambient < 1.0) or math.isnan(ambient):
        raise ConditionError(f"ambient must be in [0, 1), got {ambient}", where="ambient")
    return float(ambient)


def canonical_condition(text: str) -> str:
    """A condition as one canonical text: the label of a named direction, else ``az=…,el=…``."""
    az, el = parse_direction(text)
    return direction_label(az, el) or format_direction(az, el)
