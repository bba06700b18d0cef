"""The lighting vocabulary: eight named directional lights and the Lambertian shading they give.

This is a contract other tools rely on (the relighting prior's condition vocabulary, the `shading`
preset, the evaluation of learned layers). The text below is normative:

- camera frame x right, y up, z toward the viewer; orthographic camera looking down −z; image row 0
  is the TOP (y up means row index decreases y).
- `left` = (−sin 60°, 0, cos 60°), `right` = (sin 60°, 0, cos 60°), `top` = (0, sin 60°, cos 60°),
  `bottom` = (0, −sin 60°, cos 60°), and `top-left`, `top-right`, `bottom-left`, `bottom-right`
  likewise with the in-plane part along the normalised diagonal (e.g. top-left =
  (−sin60/√2, sin60/√2, cos60)). `LIGHTS: dict[str, tuple[float,float,float]]` with exactly these
  eight names in a fixed order (`VOCABULARY`).
- shading = a + (1 − a)·max(0, n·l) with ambient a = 0.25 by default; the wall faces the camera
  (n = +z), so the wall's shading is a + (1−a)·cos 60° = 0.625 with no shadows; optional cast
  shadows (a point is in shadow when the light ray toward l hits an object: then shading = a).
- image = albedo × shading.
- **any direction** (az, el) in degrees: azimuth in the image plane measured from +x (right)
  counter-clockwise toward +y (up), so right = 0°, top = 90°, left = 180°, bottom = 270°, wrapped to
  [0, 360); elevation = the angle from the view axis +z, in [0, 90). Its unit vector is
  l = (sin el·cos az, sin el·sin az, cos el). The named lights are the directions el = 60° and
  az = 0 (right), 45 (top-right), 90 (top), 135 (top-left), 180 (left), 225 (bottom-left),
  270 (bottom), 315 (bottom-right) — ``named_direction``; their vectors are exactly `LIGHTS` (the
  closed form agrees to 1e-15, and ``direction_vector`` returns the `LIGHTS` entry itself for a named
  direction, so a label and its angles render the same bits). A condition is a named label or the
  text ``az=A,el=E`` (or ``el=E,az=A``), parsed torch-free by `lasagna.document.condition`; the
  wall's shading under any direction is a + (1−a)·cos el.

The additive-light task (the `light` preset) has a vocabulary of its own, `GLOW_VOCABULARY`: the
colour of a point light added to the image. `warm` = HSV hue in [0.03, 0.11] (amber to orange),
saturation in [0.45, 0.80]; `cool` = hue in [0.53, 0.62] (cyan to blue), saturation in
[0.35, 0.70]; `white` = any hue, saturation ≤ 0.06; value 1 for all (max component 1). Where the
light sits is in `lasagna.world.params` (a fill light in front of the scene, near the view axis).

Decisions this module documents (the rest of `lasagna.world` follows them):

- **Shadows are off by default** (`shadows=False` everywhere): the shading is then a pointwise
  function of the normal, the wall is exactly 0.625, and a per-pixel shading layer can represent the
  truth. `shadows=True` casts exact shadows: the light ray from each visible point is intersected
  analytically with every object of the scene (not a height-field approximation), so objects
  floating before the wall shadow the wall and each other correctly.
- **The world is defined on stored (sRGB-encoded) values**: image_values = albedo_values × shading,
  with no decoding. A ground-truth stack therefore uses ``blend_space: "srgb"``, where the document
  engine multiplies the stored values directly, and `composite.png` equals the rendered image to
  within 8-bit quantisation.
"""

from __future__ import annotations

import math

import torch

from lasagna.compose.surface import lambert as lambert  # re-exported: the one shading model
from lasagna.document.condition import AMBIENT as AMBIENT  # re-exported: the contract's default ambient
from lasagna.document.condition import (
    NAMED_DIRECTIONS,
    canonical_condition,
    direction_label,
    format_direction,
    parse_direction,
    unit_vector,
)
from lasagna.document.condition import check_ambient as check_ambient  # re-exported
from lasagna.document.condition import (
    named_direction as named_direction,  # re-exported: (az, el) of a label, beside its vector
)
from lasagna.errors import ConditionError

VOCABULARY: tuple[str, ...] = tuple(NAMED_DIRECTIONS)
"""The eight named lights in their fixed order: `lasagna.document.condition.NAMED_DIRECTIONS`'s, the one list."""


def _named_vector(az: float, el: float) -> tuple[float, float, float]:
    """The exact vector of a named light (az a multiple of 45°): the in-plane part is ±sin el along an axis or
    ±sin el/√2 along a diagonal, not the closed form's cos/sin of π-multiples (1e-16 off zero)."""
    if az % 45.0 != 0.0:
        raise ValueError(f"a named light's azimuth must be a multiple of 45°, got {az!r}")
    a = math.radians(az)
    dx, dy = round(math.cos(a) * math.sqrt(2.0)), round(math.sin(a) * math.sqrt(2.0))  # each in {-1, 0, 1}
    s = math.sin(math.radians(el))
    if dx != 0 and dy != 0:
        s = s / math.sqrt(2.0)
    return (dx * s + 0.0, dy * s + 0.0, math.cos(math.radians(el)))


LIGHTS: dict[str, tuple[float, float, float]] = {name: _named_vector(*d) for name, d in NAMED_DIRECTIONS.items()}
"""The unit vector of each named light (module docstring), derived from `NAMED_DIRECTIONS`."""


WALL_SHADING = AMBIENT + (1.0 - AMBIENT) * LIGHTS["top"][2]
"""The unshadowed wall's shading with the default ambient (n = +z, so n·l = cos 60° = 0.5): 0.625."""


GLOW_VOCABULARY: tuple[str, ...] = ("warm", "cool", "white")
GLOW_TONES: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {
    "warm": ((0.03, 0.11), (0.45, 0.80)),
    "cool": ((0.53, 0.62), (0.35, 0.70)),
    "white": ((0.0, 1.0), (0.0, 0.06)),
}
"""(HSV hue range, saturation range) of each glow label; value is 1."""
assert tuple(GLOW_TONES) == GLOW_VOCABULARY


def _index_in(vocabulary: tuple[str, ...], label: str, kind: str) -> int:
    try:
        return vocabulary.index(label)
    except ValueError:
        raise ConditionError(
            f"unknown {kind} label {label!r}; expected one of {', '.join(vocabulary)}", where=kind
        ) from None


def glow_label_index(label: str) -> int:
    """Position of ``label`` in `GLOW_VOCABULARY`; raises `ConditionError` for an unknown name."""
    return _index_in(GLOW_VOCABULARY, label, "glow")


def glow_rgb(label: str, u_hue: float, u_sat: float) -> list[float]:
    """The RGB colour (max component 1) of a ``label`` glow at tone (u_hue, u_sat) ∈ [0, 1]²."""
    import colorsys

    glow_label_index(label)  # an unknown label is one clear ConditionError
    (h0, h1), (s0, s1) = GLOW_TONES[label]
    return list(colorsys.hsv_to_rgb(h0 + (h1 - h0) * float(u_hue), s0 + (s1 - s0) * float(u_sat), 1.0))


def label_index(label: str) -> int:
    """Position of ``label`` in `VOCABULARY`; raises `ConditionError` for an unknown name."""
    return _index_in(VOCABULARY, label, "light")


def light_vectors(
    labels: list[str] | tuple[str, ...], dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> torch.Tensor:
    """Unit light directions for ``labels``: (B, 3) in the camera frame."""
    rows = [LIGHTS[VOCABULARY[label_index(name)]] for name in labels]
    return torch.tensor(rows, dtype=dtype, device=device).reshape(len(rows), 3)


# ---- any direction ----------------------------------------------------------------------------------
# A light vector given as a tensor must be unit length to this tolerance (float32 rounding of a unit
# vector is ~1e-7; anything further off is a mistake to report, not to renormalise silently).
_UNIT_TOL = 1e-5
# Angles recovered from a vector (atan2/acos) are rounded to this many decimals of a degree for the
# scene's label only: the vector itself is what lights the scene.
_LABEL_DECIMALS = 6


def direction_vector(az: float, el: float) -> tuple[float, float, float]:
    """The unit light vector (sin el·cos az, sin el·sin az, cos el) of (az, el) in degrees (float64).

    A named direction returns its `LIGHTS` vector itself (equal to the closed form to 1e-15).
    """
    label = direction_label(az, el)  # also checks el ∈ [0, 90) and finiteness
    if label is not None:
        return LIGHTS[label]
    return unit_vector(az, el)


def condition_direction(condition: str) -> tuple[float, float, float]:
    """The unit light vector of a condition: a named label (its `LIGHTS` vector) or ``az=…,el=…``."""
    return direction_vector(*parse_direction(condition))


def vector_condition(light: tuple[float, float, float] | list[float]) -> str:
    """The condition text of a unit light vector: its label if it is exactly a `LIGHTS` vector, else
    ``az=…,el=…`` with the angles rounded to 1e-6° (a display label: the vector is the truth)."""
    x, y, z = (float(v) for v in light)
    for name, vec in LIGHTS.items():
        if (x, y, z) == vec:
            return name
    az = round(math.degrees(math.atan2(y, x)), _LABEL_DECIMALS)
    el = round(math.degrees(math.acos(max(-1.0, min(1.0, z)))), _LABEL_DECIMALS)
    return canonical_condition(format_direction(az, el))


def resolve_lights(
    light: str | list[str] | tuple[str, ...] | torch.Tensor, count: int
) -> tuple[torch.Tensor, list[str]]:
    """``count`` float64 unit light vectors (count, 3) and their canonical conditions, from one condition,
    one per scene, or a tensor of unit vectors (3,) or (count, 3) with z > 0 (a light in front of the wall)."""
    if isinstance(light, torch.Tensor):
        vec = light.detach().to(device="cpu", dtype=torch.float64)
        if vec.dim() == 1:
            vec = vec.expand(count, -1) if vec.shape == (3,) else vec
        if vec.shape != (count, 3):
            raise ConditionError(
                f"expected light vectors of shape (3,) or ({count}, 3), got {tuple(light.shape)}", "light"
            )
        norm = vec.norm(dim=1)
        if not bool(((norm - 1.0).abs() <= _UNIT_TOL).all()) or not bool((vec[:, 2] > 0).all()):
            raise ConditionError(
                f"expected unit light vectors with z > 0 (|l| within {_UNIT_TOL} of 1), got norms "
                f"{norm.tolist()} and z {vec[:, 2].tolist()}",
                "light",
            )
        vec = vec.contiguous()
        return vec, [vector_condition(v) for v in vec.tolist()]
    names = [light] * count if isinstance(light, str) else list(light)
    if len(names) != count:
        raise ConditionError(f"expected 1 or {count} light conditions, got {len(names)}", "light")
    conditions = [canonical_condition(n) for n in names]
    vec = torch.tensor([condition_direction(c) for c in conditions], dtype=torch.float64).reshape(count, 3)
    return vec, conditions
