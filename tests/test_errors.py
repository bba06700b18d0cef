"""``lasagna.errors``: a message and a place kept apart (``str`` joins them as before), moving an error to
another place, and the one formatter of pydantic errors."""

from __future__ import annotations

import pytest
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from lasagna.errors import DocumentError, ImageError, LasagnaError, describe_validation_error


def test_message_and_where_are_kept_apart():
    err = ImageError("too large; expected at most 4 pixels", "a.png")
    assert (err.message, err.where) == ("too large; expected at most 4 pixels", "a.png")
    assert str(err) == "a.png: too large; expected at most 4 pixels"
    bare = LasagnaError("nothing to export")
    assert (bare.message, bare.where, str(bare)) == ("nothing to export", None, "nothing to export")


def test_at_moves_an_error_and_keeps_its_class_and_message():
    moved = ImageError("corrupt", "x.png").at("stack.json: layers[1].source (x.png)")
    assert type(moved) is ImageError and moved.message == "corrupt"
    assert str(moved) == "stack.json: layers[1].source (x.png): corrupt"


class _Config(BaseModel):
    model_config = ConfigDict(extra="forbid")
    lr: float = Field(1e-3, gt=0)
    steps: int = Field(1, ge=1)


@pytest.mark.parametrize(
    "data,where,prefix,expected",
    [
        ({"lr": 0}, None, "", "lr: got 0; expected greater than 0"),
        ({"lr": 0}, "run.json", "", "run.json: lr: got 0; expected greater than 0"),
        ({"lr": 0, "steps": 0}, None, "train-layer", "train-layer.lr: got 0; expected greater than 0 (+1 more)"),
        (
            {"step": 1},
            "c.json",
            "config",
            "c.json: config.step: unknown field; expected one of lr, steps; did you mean 'steps'?",
        ),
    ],
)
def test_one_formatter_for_validation_errors(data, where, prefix, expected):
    with pytest.raises(ValidationError) as exc:
        _Config.model_validate(data)
    err = describe_validation_error(exc.value, where, _Config, DocumentError, prefix=prefix)
    assert type(err) is DocumentError and str(err) == expected


@pytest.mark.parametrize(
    "name,shown",
    [
        ("a\nb.png", "a\\nb.png"),
        ("tab\there.png", "tab\\there.png"),
        ("esc\x1b[31m.png", "esc\\x1b[31m.png"),
        ("bad\udcff.png", "bad\\udcff.png"),  # an undecodable byte of a file name (surrogateescape)
        ("line\u2028sep.png", "line\\u2028sep.png"),
        ("plain é.png", "plain é.png"),
    ],
)
def test_names_with_control_characters_stay_on_one_line(name, shown):
    """Issue #28 (17): the one place errors are formatted escapes what would break the line (as repr does)."""
    err = ImageError("cannot decode; expected a PNG", name)
    assert str(err) == f"{shown}: cannot decode; expected a PNG"
    assert str(err).isprintable() and err.where == name  # the place itself is kept as it is
    assert str(LasagnaError(f"{name} is missing")) == f"{shown} is missing"
