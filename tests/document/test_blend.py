"""Blend names: canonical modes, aliases, and the error that lists both."""

from __future__ import annotations

import pytest

from lasagna.document import BLEND_ALIASES, BLEND_MODES, canonical_blend
from lasagna.errors import DocumentError


def test_canonical_names_map_to_themselves():
    assert BLEND_MODES[:4] == ("normal", "multiply", "plus", "screen")  # the first release's order is kept
    assert BLEND_MODES[4:] == (
        "overlay",
        "darken",
        "lighten",
        "color-dodge",
        "color-burn",
        "hard-light",
        "soft-light",
        "difference",
        "exclusion",
        "hue",
        "saturation",
        "color",
        "luminosity",
        # Photoshop's other modes
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
    )
    assert [canonical_blend(m) for m in BLEND_MODES] == list(BLEND_MODES)


@pytest.mark.parametrize(
    ("alias", "mode"), [("alpha-linear", "normal"), ("multiply-luminosity", "multiply"), ("additive", "plus")]
)
def test_aliases(alias, mode):
    assert BLEND_ALIASES[alias] == mode
    assert canonical_blend(alias) == mode


@pytest.mark.parametrize(
    ("name", "hint"), [("mutiply", "multiply"), ("Screen", "screen"), ("alpha_linear", "alpha-linear")]
)
def test_unknown_names_list_valid_ones_and_suggest(name, hint):
    with pytest.raises(DocumentError) as info:
        canonical_blend(name)
    message = str(info.value)
    assert f"unknown blend {name!r}; expected one of normal, multiply, plus, screen" in message
    assert "alpha-linear -> normal" in message and "additive -> plus" in message
    assert message.endswith(f"did you mean '{hint}'?")


def test_non_string_is_refused():
    with pytest.raises(DocumentError, match="blend must be a string, got 3"):
        canonical_blend(3)
    with pytest.raises(DocumentError, match="unknown blend 'grain-merge'; expected"):
        canonical_blend("grain-merge")  # GIMP's and Krita's, not Photoshop's
