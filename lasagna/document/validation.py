"""Turning bad input into one teaching line: JSON syntax errors, rule errors and pydantic validation errors.

``format_validation_error`` condenses a pydantic ``ValidationError`` into
``where: layers[2].blend: unknown blend 'mutiply'; expected one of … (+1 more)`` with the package's one
formatter (``lasagna.errors.describe_validation_error``), as a ``DocumentError``.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from lasagna.atomic import open_regular
from lasagna.errors import DocumentError, describe_validation_error
from lasagna.limits import MAX_DOCUMENT_BYTES, MAX_INT_DIGITS, MAX_JSON_DEPTH, format_size


class RuleError(DocumentError):
    """A document rule broken at ``loc`` *relative to the validator that raised it*.

    Model-level validators see a whole object; ``loc`` lets them point at the field at fault
    (``("layers", 3, "id")``) so the reported path is exact.
    """

    def __init__(self, message: str, loc: tuple[str | int, ...] = ()):
        self.loc = loc
        super().__init__(message)


# ---- JSON --------------------------------------------------------------------------------------


def _no_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    # json.loads keeps the last of two equal keys; a file saying "blend" twice is ambiguous.
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise DocumentError(f"duplicate key {key!r} in one JSON object; expected each key once")
        out[key] = value
    return out


def _no_constants(name: str) -> Any:
    raise DocumentError(f"{name} is not valid JSON; expected a finite number")


def _int(text: str) -> int:
    # CPython refuses > 4300 digits with a ValueError of its own; no document field needs more than a few.
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise DocumentError(f"an integer of {len(text)} digits; expected at most {MAX_INT_DIGITS} digits")
    return int(text)


def _float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):  # 1e999 parses as inf
        raise DocumentError(f"{text[:40]} overflows a float; expected a finite number")
    return value


# A JSON string (escapes included): removed before brackets are counted, so "[[[" inside one is not nesting.
_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')


_NOT_BRACKETS = re.compile(r"[^\[\]{}]+")


def json_depth(text: str, stop: int = MAX_JSON_DEPTH) -> int:
    """The deepest nesting of ``[``/``{`` in JSON ``text``, without recursion; the scan stops once it
    passes ``stop`` (the answer is then ``stop + 1``)."""
    depth = deepest = 0
    for c in _NOT_BRACKETS.sub("", _JSON_STRING.sub("", text)):
        depth += 1 if c in "[{" else -1
        if depth > deepest:
            deepest = depth
            if deepest > stop:
                break
    return deepest


def parse_json(text: str, where: str) -> Any:
    """``json.loads`` that reports syntax errors as one line with line and column, and refuses what would
    exhaust the parser: more than ``MAX_JSON_DEPTH`` nested brackets, integers of more than
    ``MAX_INT_DIGITS`` digits, numbers that overflow to infinity (``lasagna.limits``)."""
    depth = json_depth(text)
    if depth > MAX_JSON_DEPTH:
        raise DocumentError(
            f"JSON nested more than {MAX_JSON_DEPTH} deep; expected at most {MAX_JSON_DEPTH} levels", where
        )
    try:
        return json.loads(
            text,
            object_pairs_hook=_no_duplicate_keys,
            parse_constant=_no_constants,
            parse_int=_int,
            parse_float=_float,
        )
    except json.JSONDecodeError as exc:
        raise DocumentError(
            f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}; expected a JSON object (see "
            "schemas/stack.schema.json)",
            where,
        ) from None
    except DocumentError as exc:
        raise DocumentError(str(exc), where) from None


def check_serialised(text: str, what: str) -> bytes:
    """``text`` as the UTF-8 bytes to write, refused (``DocumentError``) where ``read_json_text`` or
    ``parse_json`` would refuse the file: over ``MAX_DOCUMENT_BYTES``, nested deeper than ``MAX_JSON_DEPTH``,
    or holding a lone surrogate (no UTF-8 form). Every writer of a document goes through it, so no writer
    writes what ``validate`` refuses."""
    try:
        data = text.encode("utf-8")
    except UnicodeEncodeError as exc:
        raise DocumentError(
            f"holds the lone surrogate {text[exc.start]!r} at character {exc.start}; expected text with a UTF-8 form",
            what,
        ) from None
    if len(data) > MAX_DOCUMENT_BYTES:
        raise DocumentError(
            f"would be {format_size(len(data))}; expected at most {format_size(MAX_DOCUMENT_BYTES)} (shorter "
            "names, metadata or fewer layers)",
            what,
        )
    if json_depth(text) > MAX_JSON_DEPTH:
        raise DocumentError(f"would nest deeper than {MAX_JSON_DEPTH} levels of JSON; expected at most that", what)
    return data


def read_json_text(path: str | os.PathLike, what: str) -> str:
    """The text of a JSON file of at most ``MAX_DOCUMENT_BYTES``, checked before it is read. ``what`` names
    the file's kind in the messages (``stack.json``, ``a preset``); a UTF-8 byte-order mark is dropped."""
    file = Path(path)
    try:
        size = file.stat().st_size
        if size > MAX_DOCUMENT_BYTES:
            raise DocumentError(
                f"is {format_size(size)}; expected {what} of at most {format_size(MAX_DOCUMENT_BYTES)}", str(file)
            )
        with open_regular(file, expected=what) as fh:  # a FIFO would block the read forever
            data = fh.read(MAX_DOCUMENT_BYTES + 1)  # the file may grow between stat and read
    except FileNotFoundError:
        raise DocumentError(f"not found; expected {what}", str(file)) from None
    except IsADirectoryError:
        raise DocumentError(f"is a folder; expected {what}", str(file)) from None
    except OSError as exc:
        raise DocumentError(f"cannot read ({exc.strerror or exc}); expected a readable {what}", str(file)) from None
    if len(data) > MAX_DOCUMENT_BYTES:
        raise DocumentError(f"grew past {format_size(MAX_DOCUMENT_BYTES)}; expected {what} of at most that", str(file))
    try:
        # utf-8-sig: editors on Windows may prepend a byte-order mark; it is not content.
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise DocumentError(f"not UTF-8 text (byte {exc.start}); expected {what} as UTF-8 JSON", str(file)) from None


# ---- pydantic errors ------------------------------------------------------------------------------


def document_error(err: ValidationError, where: str | None, model: type[BaseModel] | None) -> DocumentError:
    """The ``DocumentError`` to raise for ``err``; its ``where`` is ``file: json.path``
    (``lasagna.errors.describe_validation_error``)."""
    return describe_validation_error(err, where, model, DocumentError)


def format_validation_error(
    err: ValidationError, where: str | None = None, model: type[BaseModel] | None = None
) -> str:
    """One line for a pydantic error: ``where: json.path: what; expected … (+N more)``."""
    return str(document_error(err, where, model))
