"""``unique_id``: the one id maker of the importers (and the editor), built on ``check_id`` (#28)."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.document.types import WINDOWS_RESERVED, check_id, unique_id


@pytest.mark.parametrize(
    "name, expected",
    [
        ("aux.png", "aux_.png"),
        ("con.x", "con_.x"),
        ("nul.a", "nul_.a"),
        ("COM1", "COM1_"),
        ("lpt9.mask.png", "lpt9_.mask.png"),
        ("Layer 1", "Layer-1"),
        ("", "layer"),
        ("..._x", "x"),
        ("é", "layer"),
    ],
)
def test_names_become_ids_check_id_accepts(name, expected):
    assert unique_id(name, set()) == expected


def test_a_clash_is_numbered_before_the_first_dot():
    taken: set[str] = set()
    assert [unique_id("aux.png", taken) for _ in range(3)] == ["aux_.png", "aux_-2.png", "aux_-3.png"]
    assert [unique_id("a.b.c", taken) for _ in range(2)] == ["a.b.c", "a-2.b.c"]
    assert unique_id("A.B.C", taken) == "A-3.B.C"  # unique case-insensitively
    assert {"aux_.png", "aux_-2.png", "a.b.c", "a-3.b.c"} <= taken


def test_every_reserved_stem_terminates():
    for word in WINDOWS_RESERVED:
        taken: set[str] = set()
        ids = [unique_id(f"{word.lower()}.png", taken) for _ in range(12)]
        assert len({i.casefold() for i in ids}) == 12
        assert all(check_id(i) == i for i in ids)


_IDISH = st.text(alphabet="abcAUXconNULlpt1.-_ 9", max_size=70)


@settings(max_examples=400, deadline=None)
@given(name=st.one_of(st.text(max_size=80), _IDISH), taken=st.sets(_IDISH.map(str.casefold), max_size=30))
def test_property_terminates_passes_check_id_and_is_new(name, taken):
    before = set(taken)
    result = unique_id(name, taken)
    assert check_id(result) == result
    assert result.casefold() not in before
    assert taken == before | {result.casefold()}


@settings(max_examples=50, deadline=None)
@given(name=_IDISH)
def test_property_many_clashes_stay_distinct(name):
    taken: set[str] = set()
    ids = [unique_id(name, taken) for _ in range(25)]
    assert len({i.casefold() for i in ids}) == 25
