"""Blend-mode names: the canonical modes of a stack document and the aliases accepted on input.

The canonical names are CSS ``mix-blend-mode``'s: every mode of W3C Compositing and Blending Level 1
(the twelve separable and four non-separable ones) plus Porter–Duff ``plus``; then Photoshop's other modes
under their Photoshop names in CSS spelling (``linear-burn`` … ``dissolve``; Krita and GIMP have all of
them). ``linear-dodge`` is Photoshop's "Linear Dodge (Add)", which clamps inside the blend and so differs
from W3C ``plus`` under partial alpha. The formulas themselves
live in the compose tier (opaque backdrop); this module only names them. Aliases are the names the
Lasagna paper uses ("alpha-linear" colour, "multiply-luminosity" shading, "additive" light); a
document may use them, but it is always written back with the canonical name, so two documents that
mean the same thing read the same.
"""

from __future__ import annotations

import difflib
from typing import Literal, get_args

from lasagna.errors import DocumentError

BlendMode = Literal[
    # the four modes of the first release (their order is kept: it is the JSON Schema's enum order)
    "normal",
    "multiply",
    "plus",
    "screen",
    # W3C Compositing Level 1, separable
    "overlay",
    "darken",
    "lighten",
    "color-dodge",
    "color-burn",
    "hard-light",
    "soft-light",
    "difference",
    "exclusion",
    # W3C Compositing Level 1, non-separable (Lum / Sat of the spec's section 10.3)
    "hue",
    "saturation",
    "color",
    "luminosity",
    # Photoshop's other modes (psd-tools' BlendMode names, CSS spelling)
    "linear-burn",
    "linear-dodge",
    "subtract",
    "divide",
    "vivid-light",
    "linear-light",
    "pin-light",
    "hard-mix",
    "darker-color",
    "lighter-color",
    "dissolve",
]

BLEND_MODES: tuple[str, ...] = get_args(BlendMode)

BLEND_ALIASES: dict[str, str] = {
    "alpha-linear": "normal",
    "multiply-luminosity": "multiply",
    "additive": "plus",
}

# Blends whose stored values may be range-mapped away from [0, 1]: a multiply factor above 1
# brightens, a negative plus darkens. For every other mode a value outside [0, 1] is not a colour.
RANGED_BLENDS: frozenset[str] = frozenset({"multiply", "plus"})

# Every name a document may contain, canonical names first (used by the JSON Schema's enum).
ACCEPTED_BLEND_NAMES: tuple[str, ...] = BLEND_MODES + tuple(BLEND_ALIASES)


def _expected() -> str:
    aliases = ", ".join(f"{alias} -> {mode}" for alias, mode in BLEND_ALIASES.items())
    return f"expected one of {', '.join(BLEND_MODES)} (aliases: {aliases})"


def canonical_blend(name: object) -> BlendMode:
    """Return the canonical name of a blend mode or alias; raise ``DocumentError`` naming the valid ones.

    Matching is exact (case-sensitive): ``"Multiply"`` is refused with a suggestion rather than
    silently corrected, like every other misspelling. ``DocumentError`` is a ``ValueError``, so
    pydantic validators report it as a validation error at the field's JSON path.
    """
    if not isinstance(name, str):
        raise DocumentError(f"blend must be a string, got {name!r}; {_expected()}")
    if name in BLEND_MODES:
        return name  # type: ignore[return-value]
    if name in BLEND_ALIASES:
        return BLEND_ALIASES[name]  # type: ignore[return-value]
    close = difflib.get_close_matches(name.lower(), ACCEPTED_BLEND_NAMES, n=1)
    hint = f"; did you mean '{close[0]}'?" if close else ""
    raise DocumentError(f"unknown blend {name!r}; {_expected()}{hint}")
