"""Turning bad input into one teaching line: JSON syntax errors, rule errors and pydantic validation errors.

``format_validation_error`` condenses a pydantic ``ValidationError`` into
``where: layers[2].blend: unknown blend 'mutiply'; expected one of … (+1 more)`` with the package's one
formatter (``lasagna.errors.describe_validation_error``), as a ``DocumentError``.
"""

from __future__ import annotations

import json
from typing import Any

from pydantic import BaseModel, ValidationError

from lasagna.errors import DocumentError, describe_validation_error


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


def parse_json(text: str, where: str) -> Any:
    """``json.loads`` that reports syntax errors as one line with line and column."""
    try:
        return json.loads(text, object_pairs_hook=_no_duplicate_keys, parse_constant=_no_constants)
    except json.JSONDecodeError as exc:
        raise DocumentError(
            f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}; expected a JSON object (see "
            "schemas/stack.schema.json)",
            where,
        ) from None
    except DocumentError as exc:
        raise DocumentError(str(exc), where) from None


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
