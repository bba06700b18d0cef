"""Turning bad input into one teaching line: JSON syntax errors and pydantic validation errors.

``format_validation_error`` condenses a pydantic ``ValidationError`` into
``where: layers[2].blend: unknown blend 'mutiply'; expected one of … (+1 more)``: the JSON path of
the first error (discriminator tags such as ``pixels`` dropped, since they are not in the file),
what was wrong, what was expected, and how many further errors there are.
"""
from __future__ import annotations

import difflib
import json
import types
import typing
from typing import Any, Iterable

from pydantic import BaseModel, ValidationError

from lasagna.errors import DocumentError


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
            f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}; expected a JSON object (see schemas/stack.schema.json)", where
        ) from None
    except DocumentError as exc:
        raise DocumentError(str(exc), where) from None


# ---- walking a model along an error location ----------------------------------------------------

def _unwrap(tp: Any) -> Any:
    """Strip ``Annotated`` and ``Optional`` so the walker sees the type that matters."""
    while True:
        origin = typing.get_origin(tp)
        if origin is typing.Annotated:
            tp = typing.get_args(tp)[0]
        elif origin in (typing.Union, types.UnionType):
            members = [a for a in typing.get_args(tp) if a is not type(None)]
            if len(members) != 1:
                return tp
            tp = members[0]
        else:
            return tp


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _tagged_member(union: Any, tag: object) -> type[BaseModel] | None:
    """The member of a discriminated union whose ``Literal`` tag field equals ``tag``."""
    for member in typing.get_args(union):
        member = _unwrap(member)
        if not _is_model(member):
            continue
        for field in member.model_fields.values():
            if typing.get_origin(field.annotation) is typing.Literal and tag in typing.get_args(field.annotation):
                return member
    return None


def _walk(model: type[BaseModel] | None, loc: Iterable[str | int]) -> tuple[list[str | int], Any]:
    """Follow ``loc`` through ``model``'s fields; return the path as the file shows it and the type there."""
    shown: list[str | int] = []
    tp: Any = model
    for part in loc:
        t = _unwrap(tp)
        if isinstance(part, int):
            args = typing.get_args(t)
            tp = args[0] if args else None
            shown.append(part)
        elif typing.get_origin(t) in (typing.Union, types.UnionType) and _tagged_member(t, part):
            tp = _tagged_member(t, part)  # a discriminator tag: not a key in the file
        elif _is_model(t) and part in t.model_fields:
            tp = t.model_fields[part].annotation
            shown.append(part)
        else:
            tp = None
            shown.append(part)
    return shown, _unwrap(tp)


def format_path(parts: Iterable[str | int]) -> str:
    """``("layers", 2, "blend")`` → ``layers[2].blend``."""
    out = ""
    for part in parts:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


# ---- one line per error --------------------------------------------------------------------------

def _short(value: Any, limit: int = 48) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _describe(error: dict[str, Any], model: type[BaseModel] | None) -> tuple[str, str]:
    kind, loc, ctx = error["type"], tuple(error["loc"]), error.get("ctx") or {}
    if kind in ("value_error", "assertion_error") and isinstance(ctx.get("error"), BaseException):
        cause = ctx["error"]
        shown, _ = _walk(model, loc + tuple(getattr(cause, "loc", ())))
        return format_path(shown), str(cause)
    if kind == "extra_forbidden":
        shown, owner = _walk(model, loc[:-1])
        key = str(loc[-1])
        if _is_model(owner):
            allowed = list(owner.model_fields)
            close = difflib.get_close_matches(key, allowed, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            return format_path(shown + [key]), f"unknown field; expected one of {', '.join(allowed)}{hint}"
        return format_path(shown + [key]), "unknown field (extra fields are forbidden)"
    shown, _ = _walk(model, loc)
    if kind == "union_tag_invalid":
        field = str(ctx.get("discriminator", "kind")).strip("'")
        return format_path(shown + [field]), f"got {ctx.get('tag')!r}; expected one of {ctx.get('expected_tags')}"
    if kind == "union_tag_not_found":
        field = str(ctx.get("discriminator", "kind")).strip("'")
        return format_path(shown + [field]), "required field is missing (it selects the kind of object)"
    if kind in ("too_short", "too_long") and "actual_length" in ctx:
        bound = f"at least {ctx.get('min_length')}" if kind == "too_short" else f"at most {ctx.get('max_length')}"
        return format_path(shown), f"got {ctx['actual_length']} items; expected {bound}"
    if kind == "missing":
        return format_path(shown), "required field is missing"
    msg: str = error["msg"]
    if msg.startswith("Input should be "):
        return format_path(shown), f"got {_short(error.get('input'))}; expected {msg[len('Input should be '):]}"
    return format_path(shown), f"{msg[:1].lower()}{msg[1:]}; got {_short(error.get('input'))}"


def _meaningful(err: ValidationError) -> list[dict[str, Any]]:
    # A field whose default is computed from other fields reports "not called" when those failed;
    # that is a consequence of the first error, not a second one.
    errors = [e for e in err.errors(include_url=False) if e["type"] != "default_factory_not_called"]
    return errors or err.errors(include_url=False)


def format_validation_error(
    err: ValidationError, where: str | None = None, model: type[BaseModel] | None = None
) -> str:
    """One line for a pydantic error: ``where: json.path: what; expected … (+N more)``.

    ``model`` (the class that was validated) lets the line drop union tags from the path and list
    the valid keys of an object that received an unknown one; without it the raw path is used.
    """
    return str(document_error(err, where, model))


def document_error(err: ValidationError, where: str | None, model: type[BaseModel] | None) -> DocumentError:
    """The ``DocumentError`` to raise for ``err``; its ``where`` is ``file: json.path``."""
    errors = _meaningful(err)
    path, message = _describe(errors[0], model)
    more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
    return DocumentError(message + more, ": ".join(p for p in (where, path) if p) or None)
