"""Light-direction conditions as text: named labels and ``az=…,el=…`` (lasagna.document.condition)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.document.condition import (
    NAMED_DIRECTIONS,
    canonical_condition,
    direction_label,
    format_direction,
    mirror_direction,
    named_direction,
    parse_direction,
    unit_vector,
    wrap_azimuth,
)
from lasagna.errors import ConditionError

AZ = st.floats(-1e6, 1e6, allow_nan=False)
EL = st.floats(0.0, 90.0, exclude_max=True)


class TestParse:
    def test_named(self):
        assert parse_direction("top-left") == (135.0, 60.0) == named_direction("top-left")
        assert [NAMED_DIRECTIONS[n][0] for n in ("right", "top", "left", "bottom")] == [0.0, 90.0, 180.0, 270.0]

    def test_both_orders_and_spaces(self):
        assert parse_direction("az=135,el=40") == (135.0, 40.0)
        assert parse_direction("el=40,az=135") == (135.0, 40.0)
        assert parse_direction(" az = 1.5e2 , el = .5 ") == (150.0, 0.5)

    @pytest.mark.parametrize(
        "text,az",
        [("az=-90,el=10", 270.0), ("az=360,el=10", 0.0), ("az=725,el=10", 5.0), ("az=-0,el=10", 0.0)],
    )
    def test_azimuth_wraps(self, text, az):
        got = parse_direction(text)[0]
        assert got == az and math.copysign(1.0, got) == 1.0

    @pytest.mark.parametrize(
        "text,why",
        [
            ("up", ""),
            ("az=10", ""),
            ("az=10,el=90", "el = 90 is outside [0, 90)"),
            ("az=10,el=-1", "el = -1 is outside [0, 90)"),
            ("az=10,az=20", "give az and el once each"),
            ("az=10,el=20,el=30", ""),
            ("az=nan,el=20", ""),
            ("az=inf,el=20", ""),
            ("AZ=10,el=20", ""),
            ("az=10;el=20", ""),
            ("", ""),
        ],
    )
    def test_bad_text_is_one_line_saying_what_is_expected(self, text, why):
        with pytest.raises(ConditionError) as info:
            parse_direction(text)
        message = str(info.value)
        assert "\n" not in message and message.startswith("condition: expected one of left, right, top")
        assert "'az=A,el=E' in degrees" in message and repr(text) in message and why in message

    def test_not_a_string(self):
        with pytest.raises(ConditionError, match="got 3"):
            parse_direction(3)  # type: ignore[arg-type]

    def test_unknown_label(self):
        with pytest.raises(ConditionError, match="light: unknown light label 'up'; expected one of left, right"):
            named_direction("up")

    def test_canonical(self):
        assert canonical_condition("el=60,az=-225") == "top-left"
        assert canonical_condition("az=135.0,el=40.00") == "az=135,el=40"
        assert direction_label(0.0, 60.0) == "right" and direction_label(1.0, 60.0) is None


@settings(max_examples=200, deadline=None)
@given(az=AZ, el=EL)
def test_format_then_parse_round_trips(az, el):
    wrapped = wrap_azimuth(az)
    assert 0.0 <= wrapped < 360.0
    assert parse_direction(format_direction(az, el)) == (wrapped, el)
    text = format_direction(az, el)
    assert parse_direction(canonical_condition(text)) == parse_direction(text)


@settings(max_examples=200, deadline=None)
@given(az=AZ, turns=st.integers(-5, 5))
def test_wrap_is_modulo_360(az, turns):
    a = wrap_azimuth(az)
    assert 0.0 <= a < 360.0
    # whole turns change nothing, up to the rounding of az + 360·k itself
    assert abs((wrap_azimuth(az + 360.0 * turns) - a + 180.0) % 360.0 - 180.0) <= 1e-9 * max(1.0, abs(az))


@settings(max_examples=100, deadline=None)
@given(el=st.floats(allow_nan=False, allow_infinity=False))
def test_elevation_bounds(el):
    if 0.0 <= el < 90.0:
        assert parse_direction(format_direction(10.0, el))[1] == el
    else:
        with pytest.raises(ConditionError, match="is outside \\[0, 90\\)"):
            format_direction(10.0, el)


@settings(max_examples=200, deadline=None)
@given(az=st.floats(0.0, 359.99), el=st.floats(0.0, 89.9), lr=st.booleans(), tb=st.booleans())
def test_a_mirrored_light_is_the_mirrored_vector(az, el, lr, tb):
    """A light in an image mirrored left-right has its x negated, top-bottom its y; the elevation is kept, and
    mirroring twice gives the light back (float64 closed form, `unit_vector`)."""
    x, y, z = unit_vector(az, el)
    mx, my, mz = unit_vector(*parse_direction(mirror_direction(format_direction(az, el), lr, tb)))
    assert math.isclose(mx, -x if lr else x, abs_tol=1e-9) and math.isclose(my, -y if tb else y, abs_tol=1e-9)
    assert math.isclose(mz, z, abs_tol=1e-12)
    back = unit_vector(*parse_direction(mirror_direction(mirror_direction(format_direction(az, el), lr, tb), lr, tb)))
    assert all(math.isclose(a, b, abs_tol=1e-9) for a, b in zip(back, (x, y, z), strict=True))
