"""What the document rules and its one writer (``Document.to_json``) guarantee: every document that can be
written, ``validate`` reads back (#28): group nesting within ``MAX_GROUP_DEPTH`` (so stack.json stays within
``MAX_JSON_DEPTH``), the serialised text within ``MAX_DOCUMENT_BYTES`` and UTF-8, names without control
characters."""

from __future__ import annotations

import pytest

from lasagna.cli import main
from lasagna.document import Document
from lasagna.document.types import check_name, sanitise_name
from lasagna.document.validation import json_depth
from lasagna.errors import DocumentError
from lasagna.io.stack import Stack, save_stack
from lasagna.limits import MAX_DOCUMENT_BYTES, MAX_GROUP_DEPTH, MAX_JSON_DEPTH


def nested(depth: int, leaf: bool = True) -> dict:
    """A document whose solid layer (or, without ``leaf``, innermost empty group) is inside ``depth`` groups."""
    inner: list[dict] = [{"id": "leaf", "kind": "solid", "color": [0.5, 0.5, 0.5]}] if leaf else []
    for i in reversed(range(depth)):
        inner = [{"id": f"g{i}", "kind": "group", "isolated": i % 2 == 0, "layers": inner}]
    return {"format": "lasagna.stack", "version": 1, "canvas": {"width": 2, "height": 2}, "layers": inner or []}


def test_groups_at_the_limit_write_json_validate_reads(tmp_path, capsys):
    doc = Document.from_dict(nested(MAX_GROUP_DEPTH))
    text = doc.to_json()
    assert json_depth(text) == MAX_JSON_DEPTH
    assert Document.from_json(text) == doc
    folder = tmp_path / "s"
    save_stack(Stack(doc, None, {}, {}), folder)
    assert main(["validate", str(folder)]) == 0, capsys.readouterr().err


@pytest.mark.parametrize("leaf", [True, False])
def test_groups_past_the_limit_are_one_line(leaf):
    with pytest.raises(DocumentError) as info:
        Document.from_dict(nested(MAX_GROUP_DEPTH + 1, leaf), where="x.json")
    message = str(info.value)
    assert "\n" not in message and f"groups nest at most {MAX_GROUP_DEPTH} deep" in message
    assert message.startswith("x.json: layers[0]" + ".layers[0]" * MAX_GROUP_DEPTH)


def test_a_stack_json_over_the_size_limit_is_never_written(tmp_path, capsys):
    name = "n" * 10_000
    layers = [{"id": f"s{i}", "name": name, "kind": "solid", "color": [0, 0, 0]} for i in range(1700)]
    doc = Document.from_dict({**nested(0), "layers": layers})
    with pytest.raises(DocumentError) as info:
        doc.to_json()
    assert "\n" not in str(info.value) and f"expected at most {MAX_DOCUMENT_BYTES // 2**20}.0 MB" in str(info.value)
    with pytest.raises(DocumentError):
        save_stack(Stack(doc, None, {}, {}), tmp_path / "s")
    assert not (tmp_path / "s" / "stack.json").exists()


def _deep(n: int) -> list:
    value: list = []
    for _ in range(n):
        value = [value]
    return value


@pytest.mark.parametrize(
    "metadata, expected",
    [
        ({"a": _deep(MAX_JSON_DEPTH)}, f"deeper than {MAX_JSON_DEPTH}"),
        ({"a": "\ud800"}, "lone surrogate"),
    ],
)
def test_metadata_validate_would_refuse_is_never_written(metadata, expected):
    doc = Document.from_dict({**nested(1), "metadata": metadata})
    with pytest.raises(DocumentError) as info:
        doc.to_json()
    assert "\n" not in str(info.value) and expected in str(info.value)


@pytest.mark.parametrize("char", ["\x00", "\x07", "\t", "\n", "\r", "\x1b", "\x7f", "\x85", "\x9f", "\ud800", "\uffff"])
def test_names_with_control_characters_are_refused(char):
    with pytest.raises(DocumentError) as info:
        Document.from_dict(
            {**nested(0), "layers": [{"id": "a", "name": f"x{char}y", "kind": "solid", "color": [0] * 3}]}
        )
    assert "\n" not in str(info.value) and "names hold no control characters" in str(info.value)
    assert sanitise_name(f"x{char}y") == "x\ufffdy" and check_name("x\ufffdy")


@pytest.mark.parametrize("name", ["Ébauche", "雲 layer", "emoji 🎨", "  spaced  ", "\u2028", "\ufffd", "a" * 5000])
def test_printable_unicode_names_are_kept(name):
    doc = Document.from_dict({**nested(0), "layers": [{"id": "a", "name": name, "kind": "solid", "color": [0] * 3}]})
    assert Document.from_json(doc.to_json()).layers[0].name == name


def test_rename_to_a_control_character_is_refused():
    doc = Document.from_dict(nested(1))
    with pytest.raises(DocumentError, match="names hold no control characters"):
        doc.replace_layer("g0", name="a\x01")
