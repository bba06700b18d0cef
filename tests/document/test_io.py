"""Loading and saving stack.json: folder or file, atomic writes, one-line errors with positions."""

from __future__ import annotations

import json

import pytest
from pydantic import ValidationError

from lasagna.document import Document, format_validation_error, load_document, save_document, stack_file
from lasagna.errors import DocumentError
from tests.document.cases import ROOT, patched, valid_stack


def test_load_from_folder_and_from_file():
    folder = ROOT / "examples" / "stacks" / "basic"
    by_folder, by_file = load_document(folder), load_document(folder / "stack.json")
    assert by_folder == by_file
    assert by_folder.ids == ("base", "shade", "sticker", "glow", "hidden")


def test_save_then_load_round_trip(tmp_path):
    doc = Document.from_dict(valid_stack())
    written = save_document(doc, tmp_path / "new-stack")
    assert written == tmp_path / "new-stack" / "stack.json"
    assert load_document(tmp_path / "new-stack") == doc
    assert written.read_text(encoding="utf-8") == doc.to_json()
    assert [p.name for p in written.parent.iterdir()] == ["stack.json"]  # no temporary file left


def test_save_to_a_json_file_replaces_it(tmp_path):
    target = tmp_path / "other.json"
    target.write_text("old", encoding="utf-8")
    save_document(Document.from_dict(valid_stack()), target)
    assert json.loads(target.read_text(encoding="utf-8"))["format"] == "lasagna.stack"
    assert stack_file(target) == target and stack_file(tmp_path) == tmp_path / "stack.json"


def test_malformed_json_names_file_line_and_column(tmp_path):
    (tmp_path / "stack.json").write_text(
        '{\n  "format": "lasagna.stack",\n  "version": 1,,\n}', encoding="utf-8"
    )  # 2nd comma: column 16
    with pytest.raises(DocumentError) as info:
        load_document(tmp_path)
    assert (
        str(info.value)
        == f"{tmp_path / 'stack.json'}: invalid JSON at line 3, column 16: Expecting property name enclosed in "
        "double quotes; expected a JSON object (see schemas/stack.schema.json)"
    )


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ('{"a": 1, "a": 2}', "duplicate key 'a' in one JSON object"),
        ('{"a": NaN}', "NaN is not valid JSON"),
        ('{"a": -Infinity}', "-Infinity is not valid JSON"),
        ("", "invalid JSON at line 1, column 1"),
    ],
)
def test_json_that_python_would_accept_is_refused(text, fragment):
    with pytest.raises(DocumentError, match=f"^mine.json: {fragment}"):
        Document.from_json(text, "mine.json")


def test_validation_error_names_file_and_json_path(tmp_path):
    (tmp_path / "stack.json").write_text(
        json.dumps(patched(valid_stack(), "layers.2.blend", "mutiply")), encoding="utf-8"
    )
    with pytest.raises(DocumentError) as info:
        load_document(tmp_path)
    assert str(info.value).startswith(
        f"{tmp_path / 'stack.json'}: layers[2].blend: unknown blend 'mutiply'; expected one of"
    )
    assert info.value.where == f"{tmp_path / 'stack.json'}: layers[2].blend"


def test_byte_order_mark_is_not_content(tmp_path):
    (tmp_path / "stack.json").write_bytes(b"\xef\xbb\xbf" + json.dumps(valid_stack()).encode())
    assert load_document(tmp_path).ids[0] == "base"


def test_missing_and_undecodable_files(tmp_path):
    with pytest.raises(DocumentError, match=r"stack\.json: not found; expected a stack folder"):
        load_document(tmp_path)
    (tmp_path / "stack.json").write_bytes(b'{"format": "\xff"}')
    with pytest.raises(DocumentError, match="not UTF-8 text"):
        load_document(tmp_path)


def test_format_validation_error_without_model_keeps_raw_path():
    try:
        Document.model_validate(patched(valid_stack(), "layers.0.opacity", 2))
    except ValidationError as err:
        assert (
            format_validation_error(err, "x.json", Document)
            == "x.json: layers[0].opacity: got 2; expected less than or equal to 1"
        )
        # Without the model the discriminator tag ("pixels") stays in the path.
        assert format_validation_error(err).startswith("layers[0].pixels.opacity: got 2")
    else:  # pragma: no cover
        pytest.fail("opacity 2 was accepted")
