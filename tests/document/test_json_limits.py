"""JSON limits (lasagna.document.validation, lasagna.limits): nesting, integer length, overflow and file
size are refused as one-line DocumentErrors before they exhaust the parser, the stack or memory."""

from __future__ import annotations

import json

import pytest

from lasagna.cli import main
from lasagna.document.validation import json_depth, parse_json, read_json_text
from lasagna.errors import DocumentError
from lasagna.limits import MAX_DOCUMENT_BYTES, MAX_INT_DIGITS, MAX_JSON_DEPTH
from tests.document.cases import valid_stack
from tests.support.bounded import cpu_seconds


def _refused(text: str) -> str:
    with pytest.raises(DocumentError) as info:
        parse_json(text, "stack.json")
    message = str(info.value)
    assert "\n" not in message and "stack.json" in message
    return message


@pytest.mark.parametrize(
    "text, depth",
    [
        ("{}", 1),
        ("[[]]", 2),
        ('{"a": [1, {"b": []}]}', 4),
        ('"[[[[[[[["', 0),  # brackets inside a string are not nesting
        ('["\\"[[[", {"k": "]]]]}"}]', 2),  # ... nor after an escaped quote
        ("1", 0),
    ],
)
def test_json_depth(text, depth):
    assert json_depth(text) == depth


def test_json_depth_stops_past_the_limit():
    assert json_depth("[" * 10_000, stop=5) == 6


def test_nesting_at_the_limit_parses_and_past_it_is_refused():
    assert parse_json("[" * MAX_JSON_DEPTH + "]" * MAX_JSON_DEPTH, "x") is not None
    message = _refused("[" * (MAX_JSON_DEPTH + 1) + "]" * (MAX_JSON_DEPTH + 1))
    assert f"more than {MAX_JSON_DEPTH} deep" in message


def test_100k_brackets_are_one_line_not_a_recursion_error():
    start = cpu_seconds()
    for text in ("[" * 10**5, "[" * 10**5 + "]" * 10**5, '{"a":' * 10**5):
        assert "nested" in _refused(text)
    assert cpu_seconds() - start < 5  # CPU seconds (a loaded machine stretches wall time); a parse takes ~0.1


def test_brackets_in_strings_do_not_count():
    value = parse_json(json.dumps({"name": "[" * 10_000}), "x")
    assert value == {"name": "[" * 10_000}


def test_long_integers_are_refused():
    assert parse_json("1" * MAX_INT_DIGITS, "x") == int("1" * MAX_INT_DIGITS)
    assert parse_json("-" + "9" * MAX_INT_DIGITS, "x") < 0
    assert f"at most {MAX_INT_DIGITS} digits" in _refused("1" * (MAX_INT_DIGITS + 1))
    assert "digits" in _refused('{"width": ' + "7" * 5000 + "}")


@pytest.mark.parametrize("text", ["1e999", "-1e999", '{"opacity": 1e400}', "[1.0e99999]"])
def test_overflowing_floats_are_refused(text):
    assert "finite" in _refused(text)


@pytest.mark.parametrize("text", ["NaN", "Infinity", "[-Infinity]"])
def test_constants_are_refused(text):
    assert "finite" in _refused(text)


def test_read_json_text_refuses_a_large_file_before_reading(tmp_path, monkeypatch):
    big = tmp_path / "stack.json"
    with open(big, "wb") as f:
        f.truncate(17 * 2**20)  # sparse: costs no disk and, unless read, no memory

    def no_read(*args, **kwargs):
        raise AssertionError("the file was opened")

    monkeypatch.setattr("builtins.open", no_read)
    with pytest.raises(DocumentError) as info:
        read_json_text(big, "a stack.json")
    assert "17.0 MB" in str(info.value) and "at most 16.0 MB" in str(info.value)


def test_read_json_text_at_the_limit_is_read(tmp_path):
    path = tmp_path / "x.json"
    path.write_bytes(b" " * (MAX_DOCUMENT_BYTES - 2) + b"{}")
    assert read_json_text(path, "x").strip() == "{}"


def test_read_json_text_encodings(tmp_path):
    path = tmp_path / "x.json"
    path.write_bytes(b'\xef\xbb\xbf{"a": "\xc3\xa9"}')  # a byte-order mark is dropped
    assert json.loads(read_json_text(path, "x")) == {"a": "é"}
    path.write_bytes(b'{"a": "\xe9"}')  # Latin-1
    with pytest.raises(DocumentError, match="not UTF-8 text"):
        read_json_text(path, "x")
    path.write_text("{}", encoding="utf-16")
    with pytest.raises(DocumentError, match="not UTF-8 text"):
        read_json_text(path, "x")


def _validate(capsys, folder) -> tuple[int, str]:
    code = main(["validate", str(folder)])
    out, err = capsys.readouterr()
    return code, err


@pytest.mark.parametrize(
    "body, message",
    [
        (b"[" * 10**5, "nested more than"),
        (b'{"format": ' + b"1" * 5000 + b"}", "digits"),
        (b'{"version": 1e999}', "overflows"),
        (b'{"format": "lasagna.stack", "x": "\xff"}', "not UTF-8"),
    ],
)
def test_validate_cli_refuses_hostile_json_in_one_line(tmp_path, capsys, body, message):
    (tmp_path / "stack.json").write_bytes(body)
    code, err = _validate(capsys, tmp_path)
    assert code == 2 and message in err, err
    assert len(err.splitlines()) == 1 and "internal error" not in err


def test_validate_cli_refuses_a_huge_stack_json(tmp_path, capsys):
    with open(tmp_path / "stack.json", "wb") as f:
        f.truncate(17 * 2**20)
    code, err = _validate(capsys, tmp_path)
    assert code == 2 and "at most 16.0 MB" in err and len(err.splitlines()) == 1


def test_a_valid_document_parses_unchanged(tmp_path):
    doc = valid_stack()
    (tmp_path / "stack.json").write_text(json.dumps(doc, indent=1))
    assert parse_json(read_json_text(tmp_path / "stack.json", "a stack.json"), "stack.json") == doc
