"""The stack document models: valid and invalid documents side by side, helpers, round trips."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from lasagna.document import (
    Canvas,
    Document,
    LearnedLayer,
    Offset,
    PixelsLayer,
    SolidLayer,
    canonical_blend,
)
from lasagna.errors import DocumentError
from tests.document.cases import DELETE, patched, valid_stack

# (what the document tries, dotted patch path, value) — each is a valid variation of valid_stack().
VALID = [
    ("minimal one-layer stack", "layers", [{"id": "a", "kind": "pixels", "source": "a.png"}]),
    ("linear blend space", "blend_space", "linear"),
    ("clamp once at the output", "clamp", "output"),
    ("offscreen negative offset", "layers.2.offset", {"x": -1000, "y": 70000}),
    ("plus with a range [0, 2]", "layers.1.blend", "plus"),
    (
        "plus with a negative range",
        "layers.1",
        {"id": "dark", "kind": "pixels", "source": "d.png", "blend": "plus", "range": [-1.0, 0.5]},
    ),
    ("range [0, 1] allowed for screen", "layers.2.blend", "screen"),
    ("RGB solid colour", "layers.2.color", [0.0, 1.0, 0.5]),
    ("solid without size (canvas)", "layers.2.size", DELETE),
    ("integers accepted as floats", "layers.0.opacity", 1),
    ("mask path", "layers.0.mask", "masks/base.png"),
    ("path with a harmless ..", "layers.0.source", "layers/x/../base.png"),
    ("path with ./", "layers.0.source", "./layers/base.png"),
    ("unicode name", "layers.0.name", "Albédo ☀"),
    ("id of 64 characters", "layers.3.id", "r" * 64),
    ("id with dots and dashes", "layers.3.id", "relit-2.v_1"),
    ("id that only starts like a device name", "layers.3.id", "console"),
    ("preset given as a path", "layers.3.preset", "./presets/mine.json"),
    (
        "learned layer without source or generator",
        "layers.3",
        {
            "id": "relit",
            "kind": "learned",
            "preset": "shading",
            "condition": {"label": "left", "prompt": "p"},
            "conditioned_on": "shade",
        },
    ),
    ("sha256 digest", "layers.3.generator.sha256", "ab" * 32),
    ("canvas at the size limit", "canvas", {"width": 32768, "height": 1}),
    ("free-form metadata", "metadata", {"author": "me", "tags": ["a", 1, None, {"k": 2.5}]}),
    ("a layer clipped to the one below", "layers.2.clip", True),
    ("a clipping chain of two", "layers.1.clip", True),
]


@pytest.mark.parametrize(("what", "path", "value"), VALID, ids=[v[0] for v in VALID])
def test_valid_documents(what, path, value):
    doc = Document.from_dict(patched(valid_stack(), path, value))
    assert doc.format == "lasagna.stack" and len(doc.layers) >= 1


# (what is wrong, patch path, value, JSON path named in the message, fragment quoting the rule,
#  whether the JSON Schema can express the rule too — used by test_schema.py)
INVALID = [
    (
        "unknown blend",
        "layers.1.blend",
        "mutiply",
        "layers[1].blend",
        "unknown blend 'mutiply'; expected one of normal, multiply, plus, screen",
        True,
    ),
    ("blend in capitals", "layers.1.blend", "Multiply", "layers[1].blend", "did you mean 'multiply'", True),
    ("unknown field", "layers.0.sorce", "x", "layers[0].sorce", "unknown field; expected one of id, name, kind", True),
    ("unknown top-level field", "colour", 1, "colour", "unknown field; expected one of format, version", True),
    ("unknown kind", "layers.0.kind", "pixel", "layers[0].kind", "expected one of 'pixels', 'solid', 'learned'", True),
    ("missing kind", "layers.0.kind", DELETE, "layers[0].kind", "required field is missing", True),
    ("pixels without source", "layers.0.source", DELETE, "layers[0].source", "required field is missing", True),
    ("solid without color", "layers.2.color", DELETE, "layers[2].color", "required field is missing", True),
    ("range for screen", "layers.1.blend", "screen", "layers[1].range", "allowed only for multiply and plus", True),
    ("range lo > hi", "layers.1.range", [2.0, 0.0], "layers[1].range", "lo < hi", False),
    ("range lo == hi", "layers.1.range", [1.0, 1.0], "layers[1].range", "lo < hi", False),
    ("range of three numbers", "layers.1.range", [0, 1, 2], "layers[1].range", "expected at most 2", True),
    ("range infinite", "layers.1.range", [0.0, float("inf")], "layers[1].range[1]", "finite number", False),
    ("opacity above 1", "layers.1.opacity", 1.5, "layers[1].opacity", "less than or equal to 1", True),
    ("opacity negative", "layers.1.opacity", -0.1, "layers[1].opacity", "greater than or equal to 0", True),
    ("opacity as a string", "layers.1.opacity", "1", "layers[1].opacity", "valid number", True),
    ("opacity NaN", "layers.1.opacity", float("nan"), "layers[1].opacity", "finite number", False),
    ("visible as 1", "layers.1.visible", 1, "layers[1].visible", "valid boolean", True),
    ("offset not integer", "layers.2.offset", {"x": 1.5, "y": 0}, "layers[2].offset.x", "valid integer", True),
    (
        "offset beyond int32",
        "layers.2.offset",
        {"x": 2**31, "y": 0},
        "layers[2].offset.x",
        "less than or equal to",
        True,
    ),
    ("source escapes with ..", "layers.0.source", "../x.png", "layers[0].source", "escapes the stack folder", True),
    (
        "source escapes deeper",
        "layers.0.source",
        "a/../../x.png",
        "layers[0].source",
        "escapes the stack folder",
        False,
    ),
    ("source absolute", "layers.0.source", "/etc/passwd", "layers[0].source", "is absolute", True),
    ("source with drive letter", "layers.0.source", "C:/x.png", "layers[0].source", "drive letter", True),
    ("source with backslash", "layers.0.source", "layers\\base.png", "layers[0].source", "backslash", True),
    ("source with empty segment", "layers.0.source", "layers//base.png", "layers[0].source", "empty segment", True),
    ("source with trailing slash", "layers.0.source", "layers/", "layers[0].source", "empty segment", True),
    ("source empty", "layers.0.source", "", "layers[0].source", "empty path", True),
    ("source is the folder", "layers.0.source", "a/..", "layers[0].source", "names the stack folder itself", False),
    ("source with a newline", "layers.0.source", "a\nb.png", "layers[0].source", "control character", True),
    ("mask absolute", "layers.1.mask", "/m.png", "layers[1].mask", "is absolute", True),
    ("id duplicated ignoring case", "layers.1.id", "BASE", "layers[1].id", "unique case-insensitively", False),
    ("id starting with a dash", "layers.1.id", "-shade", "layers[1].id", "ids match ^[A-Za-z0-9]", True),
    ("id with a slash", "layers.1.id", "a/b", "layers[1].id", "ids match", True),
    ("id of 65 characters", "layers.1.id", "s" * 65, "layers[1].id", "ids match", True),
    ("id with a trailing newline", "layers.1.id", "shade\n", "layers[1].id", "ids match", False),
    ("id a Windows device name", "layers.1.id", "Aux", "layers[1].id", "reserved device name", True),
    ("id a device name with a dot", "layers.1.id", "com1.x", "layers[1].id", "reserved device name", True),
    ("id not a string", "layers.1.id", 7, "layers[1].id", "valid string", True),
    (
        "conditioned_on above",
        "layers.3.conditioned_on",
        "nothing",
        "layers[3].conditioned_on",
        "names a layer below",
        False,
    ),
    (
        "conditioned_on itself",
        "layers.3.conditioned_on",
        "relit",
        "layers[3].conditioned_on",
        "names a layer below",
        False,
    ),
    (
        "conditioned_on in other case",
        "layers.3.conditioned_on",
        "BASE",
        "layers[3].conditioned_on",
        "names a layer below",
        False,
    ),
    ("preset path escapes", "layers.3.preset", "../p.json", "layers[3].preset", "escapes the stack folder", True),
    ("preset name invalid", "layers.3.preset", "my preset", "layers[3].preset", "ids match", True),
    (
        "condition label empty",
        "layers.3.condition.label",
        "",
        "layers[3].condition.label",
        "at least 1 character",
        True,
    ),
    (
        "condition without label",
        "layers.3.condition",
        {},
        "layers[3].condition.label",
        "required field is missing",
        True,
    ),
    (
        "sha256 in capitals",
        "layers.3.generator.sha256",
        "AB" * 32,
        "layers[3].generator.sha256",
        "64 lower-case hex",
        True,
    ),
    (
        "generator path absolute",
        "layers.3.generator.checkpoint",
        "/w.safetensors",
        "layers[3].generator.checkpoint",
        "is absolute",
        True,
    ),
    ("settings not an object", "layers.3.settings", [], "layers[3].settings", "valid dictionary", True),
    (
        "colour component above 1",
        "layers.2.color",
        [1.0, 2.0, 0.0],
        "layers[2].color[1]",
        "less than or equal to 1",
        True,
    ),
    ("colour of two components", "layers.2.color", [1.0, 0.0], "layers[2].color", "expected at least 3", True),
    ("colour of five components", "layers.2.color", [0, 0, 0, 0, 0], "layers[2].color", "expected at most 4", True),
    (
        "solid size zero",
        "layers.2.size",
        {"width": 0, "height": 4},
        "layers[2].size.width",
        "greater than or equal to 1",
        True,
    ),
    ("canvas too wide", "canvas.width", 32769, "canvas.width", "less than or equal to 32768", True),
    ("canvas width zero", "canvas.width", 0, "canvas.width", "greater than or equal to 1", True),
    ("canvas width a float", "canvas.width", 64.5, "canvas.width", "valid integer", True),
    ("background with alpha", "canvas.background", [0, 0, 0, 1], "canvas.background", "expected at most 3", True),
    ("wrong format", "format", "lasagna.stacks", "format", "expected 'lasagna.stack'", True),
    ("missing format", "format", DELETE, "format", "required field is missing", True),
    ("version 2", "version", 2, "version", "expected 1", True),
    ("no layers", "layers", [], "layers", "expected at least 1", True),
    ("unknown blend space", "blend_space", "rgb", "blend_space", "expected 'srgb' or 'linear'", True),
    ("unknown clamp", "clamp", "none", "clamp", "expected 'layer' or 'output'", True),
    ("empty name", "layers.0.name", "", "layers[0].name", "at least 1 character", True),
    ("name with a control character", "layers.0.name", "a\x07b", "layers[0].name", "no control characters", True),
    ("name with a C1 control", "layers.1.name", "a\x85", "layers[1].name", "no control characters", True),
    ("name with a lone surrogate", "layers.0.name", "a\ud800", "layers[0].name", "no control characters", False),
    ("metadata not an object", "metadata", [1], "metadata", "valid dictionary", True),
    ("the bottom layer clipped", "layers.0.clip", True, "layers[0].clip", "clips to the layer below it", False),
    ("clip not a boolean", "layers.1.clip", "yes", "layers[1].clip", "valid boolean", True),
]


@pytest.mark.parametrize(
    ("what", "path", "value", "json_path", "rule", "in_schema"), INVALID, ids=[c[0] for c in INVALID]
)
def test_invalid_documents(what, path, value, json_path, rule, in_schema):
    with pytest.raises(DocumentError) as info:
        Document.from_dict(patched(valid_stack(), path, value), "stack.json")
    message = str(info.value)
    assert message.startswith(f"stack.json: {json_path}: "), message
    assert rule in message, message
    assert "\n" not in message  # one line, even when the bad value holds a newline


def test_invalid_documents_raise_validation_error_from_the_model():
    # The plain pydantic entry point still raises pydantic's error (for code that expects it).
    with pytest.raises(ValidationError):
        Document.model_validate(patched(valid_stack(), "layers.1.blend", "mutiply"))


def test_several_errors_are_counted():
    doc = patched(patched(valid_stack(), "layers.1.opacity", 3.0), "canvas.width", 0)
    with pytest.raises(DocumentError, match=r"^stack\.json: canvas\.width: .*\(\+1 more\)$"):
        Document.from_dict(doc, "stack.json")


def test_aliases_are_accepted_and_written_canonical():
    doc = valid_stack()
    doc["layers"][0]["blend"] = "alpha-linear"
    doc["layers"][1]["blend"] = "multiply-luminosity"
    doc["layers"][3]["blend"] = "additive"
    parsed = Document.from_dict(doc)
    assert [layer.blend for layer in parsed.layers] == ["normal", "multiply", "normal", "plus"]
    text = parsed.to_json()
    for alias in ("alpha-linear", "multiply-luminosity", "additive"):
        assert alias not in text
    assert canonical_blend("additive") == "plus"


def test_defaults_are_filled_and_written_explicitly():
    doc = Document.from_dict(valid_stack())
    tint = doc.layer("tint")
    assert isinstance(tint, SolidLayer)
    assert (tint.name, tint.opacity, tint.visible, tint.range, tint.mask) == ("tint", 1.0, True, (0.0, 1.0), None)
    written = json.loads(doc.to_json())["layers"][2]
    assert written["name"] == "tint" and written["range"] == [0.0, 1.0] and written["mask"] is None
    assert isinstance(doc.layers[0], PixelsLayer) and isinstance(doc.layers[3], LearnedLayer)


def test_round_trip_is_stable():
    doc = Document.from_dict(valid_stack())
    text = doc.to_json()
    again = Document.from_json(text)
    assert again == doc
    assert again.to_json() == text
    assert text.endswith("}\n") and text.startswith('{\n  "format": "lasagna.stack",\n  "version": 1,')
    assert '"range": [0.0, 2.0]' in text  # short arrays stay on one line


def test_models_are_frozen():
    doc = Document.from_dict(valid_stack())
    with pytest.raises(ValidationError):
        doc.layers[0].opacity = 0.5  # type: ignore[misc]
    with pytest.raises(ValidationError):
        doc.clamp = "output"  # type: ignore[misc]


def test_built_from_python_objects():
    doc = Document(
        format="lasagna.stack",
        version=1,
        canvas=Canvas(width=8, height=8),
        layers=[PixelsLayer(id="a", kind="pixels", source="a.png", offset=Offset(x=-2, y=3), range=(0, 1))],
    )
    assert doc.layers[0].offset == Offset(x=-2, y=3) and doc.layers[0].range == (0.0, 1.0)
    assert doc.canvas.background == (0.0, 0.0, 0.0)
    # In Python the kind defaults to the class's tag; a file must state it (see INVALID "missing kind").
    assert (
        SolidLayer(id="s", color=(1, 0, 0)).kind == "solid"
        and LearnedLayer(id="l", preset="shading", condition={"label": "left"}, conditioned_on="a").kind == "learned"
    )


class TestHelpers:
    def test_lookup(self):
        doc = Document.from_dict(valid_stack())
        assert doc.ids == ("base", "shade", "tint", "relit")
        assert doc.index("tint") == 2 and doc.layer("shade").blend == "multiply"
        with pytest.raises(DocumentError, match="no layer with id 'Tint'; expected one of base, shade, tint, relit"):
            doc.index("Tint")

    def test_replace_layer_validates(self):
        doc = Document.from_dict(valid_stack())
        changed = doc.replace_layer("tint", opacity=0.5, blend="additive")
        assert changed.layer("tint").opacity == 0.5 and changed.layer("tint").blend == "plus"
        assert doc.layer("tint").opacity == 1.0  # the original is untouched
        with pytest.raises(DocumentError, match=r"^layers\[2\]\.opacity: got 2"):
            doc.replace_layer("tint", opacity=2)

    def test_with_layer_inserts_or_replaces(self):
        doc = Document.from_dict(valid_stack())
        top = doc.with_layer({"id": "top", "kind": "solid", "color": [1, 1, 1]})
        assert top.ids[-1] == "top" and len(top.layers) == 5
        bottom = doc.with_layer(SolidLayer(id="under", kind="solid", color=(0, 0, 0)), index=0)
        assert bottom.ids[0] == "under"
        replaced = doc.with_layer(PixelsLayer(id="tint", kind="pixels", source="t.png"))
        assert replaced.ids == doc.ids and isinstance(replaced.layer("tint"), PixelsLayer)
        with pytest.raises(DocumentError, match=r"^layers\[4\]\.opacity: got 3"):
            doc.with_layer({"id": "top", "kind": "solid", "color": [1, 1, 1], "opacity": 3})
        with pytest.raises(DocumentError, match="already exists"):
            doc.with_layer(PixelsLayer(id="tint", kind="pixels", source="t.png"), index=0)

    def test_without_layer_keeps_references_valid(self):
        doc = Document.from_dict(valid_stack())
        assert doc.without_layer("tint").ids == ("base", "shade", "relit")
        with pytest.raises(DocumentError, match=r"layers\[2\]\.conditioned_on: 'base' is not the id of a layer below"):
            doc.without_layer("base")

    def test_replace_top_level(self):
        doc = Document.from_dict(valid_stack())
        assert doc.replace(blend_space="linear").blend_space == "linear"
        with pytest.raises(DocumentError, match="^blend_space: got 'lin'"):
            doc.replace(blend_space="lin")


def test_clip_is_written_only_when_set_and_chains_are_found():
    from lasagna.document import clip_chains

    doc = Document.from_dict(patched(patched(valid_stack(), "layers.1.clip", True), "layers.2.clip", True))
    assert '"clip": true' in doc.to_json() and doc.to_json().count('"clip"') == 2
    assert '"clip"' not in Document.from_dict(valid_stack()).to_json()
    assert Document.from_json(doc.to_json()) == doc
    assert [(b.id, [c.id for c in cs]) for b, cs in clip_chains(doc.layers)] == [
        ("base", ["shade", "tint"]),
        (doc.layers[3].id, []),
    ]
