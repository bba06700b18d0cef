"""Property tests: random valid documents round-trip exactly and satisfy the JSON Schema; random
ids and paths are either refused or genuinely safe."""

from __future__ import annotations

import posixpath
import re

from hypothesis import given, settings
from hypothesis import strategies as st
from jsonschema import Draft202012Validator

from lasagna.document import Document, check_id, check_relative_path, schemas
from lasagna.document.types import ID_PATTERN, PATH_PATTERN, WINDOWS_RESERVED, range_problem
from lasagna.errors import DocumentError

STACK_SCHEMA = Draft202012Validator(schemas()["stack.schema.json"])
RESERVED = re.compile(schemas()["stack.schema.json"]["$defs"]["PixelsLayer"]["properties"]["id"]["not"]["pattern"])

ids = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,15}", fullmatch=True).filter(
    lambda s: s.split(".")[0].upper() not in WINDOWS_RESERVED
)
segments = st.from_regex(r"[A-Za-z0-9_-][A-Za-z0-9_. -]{0,8}", fullmatch=True)
paths = st.lists(segments, min_size=1, max_size=3).map("/".join)
unit = st.floats(0.0, 1.0)
finite = st.floats(-1e6, 1e6, allow_nan=False)
blends = st.sampled_from(["normal", "multiply", "plus", "screen", "alpha-linear", "multiply-luminosity", "additive"])
RANGED = {"multiply", "plus", "multiply-luminosity", "additive"}


# The name rule (check_name): no control characters, surrogates or U+FFFE/U+FFFF.
_NAME_CHARS = st.characters(blacklist_categories=("Cc", "Cs"), blacklist_characters="\ufffe\uffff")
_UTF8_CHARS = st.characters(blacklist_categories=("Cs",))  # free text: anything stack.json can hold as UTF-8


@st.composite
def layers(draw, id_: str, below: list[str]) -> dict:
    kinds = ["pixels", "solid"] + (["learned"] if below else [])
    kind = draw(st.sampled_from(kinds))
    layer: dict = {"id": id_, "kind": kind}
    blend = draw(blends)
    if draw(st.booleans()):
        layer["blend"] = blend
    if layer.get("blend") in RANGED and draw(st.booleans()):
        # The range rule (range_problem): lo < hi, and a span float32 holds.
        lo, hi = sorted(draw(st.tuples(finite, finite).filter(lambda t: range_problem(*sorted(t)) is None)))
        layer["range"] = [lo, hi]
    for key, strategy in [
        ("opacity", unit),
        ("visible", st.booleans()),
        ("name", st.text(_NAME_CHARS, min_size=1, max_size=8)),
        ("offset", st.fixed_dictionaries({"x": st.integers(-5000, 5000), "y": st.integers(-5000, 5000)})),
        ("mask", st.none() | paths),
    ]:
        if draw(st.booleans()):
            layer[key] = draw(strategy)
    if kind == "pixels":
        layer["source"] = draw(paths)
    elif kind == "solid":
        layer["color"] = draw(st.lists(unit, min_size=3, max_size=4))
        if draw(st.booleans()):
            layer["size"] = {"width": draw(st.integers(1, 32768)), "height": draw(st.integers(1, 32768))}
    else:
        layer.update(
            preset=draw(ids),
            condition={"label": draw(st.text(_UTF8_CHARS, min_size=1, max_size=6))},
            conditioned_on=draw(st.sampled_from(below)),
        )
        if draw(st.booleans()):
            layer["generator"] = {
                "checkpoint": draw(paths),
                "sha256": draw(st.none() | st.from_regex(r"[0-9a-f]{64}", fullmatch=True)),
            }
        if draw(st.booleans()):
            layer["settings"] = {"steps": draw(st.integers(1, 500)), "note": draw(st.text(_UTF8_CHARS, max_size=5))}
    return layer


@st.composite
def documents(draw) -> dict:
    names = draw(st.lists(ids, min_size=1, max_size=5, unique_by=str.casefold))
    stack = [draw(layers(id_, names[:i])) for i, id_ in enumerate(names)]
    doc = {
        "format": "lasagna.stack",
        "version": 1,
        "layers": stack,
        "canvas": {"width": draw(st.integers(1, 32768)), "height": draw(st.integers(1, 32768))},
    }
    if draw(st.booleans()):
        doc["canvas"]["background"] = draw(st.lists(unit, min_size=3, max_size=3))
    if draw(st.booleans()):
        doc["blend_space"] = draw(st.sampled_from(["srgb", "linear"]))
    if draw(st.booleans()):
        doc["clamp"] = draw(st.sampled_from(["layer", "output"]))
    return doc


@settings(max_examples=60, deadline=None)
@given(documents())
def test_valid_documents_round_trip_and_satisfy_the_schema(data):
    assert list(STACK_SCHEMA.iter_errors(data)) == []  # the schema is never stricter than the models
    doc = Document.from_dict(data)
    text = doc.to_json()
    again = Document.from_json(text)
    assert again == doc and again.to_json() == text
    assert all(layer.blend in ("normal", "multiply", "plus", "screen") for layer in again.layers)
    assert list(STACK_SCHEMA.iter_errors(again.to_dict())) == []


awkward = st.text(st.sampled_from(list("ab./\\:C-_ \n\x00")) | st.characters(), max_size=14)


@settings(max_examples=300, deadline=None)
@given(awkward)
def test_paths_are_refused_or_stay_inside_the_folder(path):
    try:
        check_relative_path(path)
    except DocumentError:
        return
    joined = posixpath.normpath(posixpath.join("/stack", path))
    assert joined.startswith("/stack/"), path  # resolves strictly inside the stack folder
    assert "\\" not in path and not path.startswith("/") and "\x00" not in path
    assert re.search(PATH_PATTERN, path), path  # and the schema agrees


@settings(max_examples=300, deadline=None)
@given(awkward | ids)
def test_ids_are_refused_or_safe_file_names(id_):
    try:
        check_id(id_)
    except DocumentError:
        return
    assert 1 <= len(id_) <= 64 and not set(id_) & set("/\\:\x00\n ") and id_[0] not in ".-_"
    assert id_.split(".")[0].upper() not in WINDOWS_RESERVED
    assert re.search(ID_PATTERN, id_) and not RESERVED.search(id_)
