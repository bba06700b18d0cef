"""Errors that teach: every Lasagna error is one line naming what was wrong, where, and what was expected.

The CLI prints ``str(error)`` and exits with status 2; no traceback reaches the user. ``str(error)`` is
one line whatever the names in it hold: control characters (a newline in a file name, an escape sequence)
are written as ``repr`` writes them (``printable``), here, once, for every error.
``describe_validation_error`` is the one place a pydantic ``ValidationError`` becomes such a line.
"""

from __future__ import annotations

import difflib
import types
import typing
from collections.abc import Iterable
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError


def printable(text: str) -> str:
    """``text`` with every non-printable character (newline, tab, escape, a file name's undecodable byte)
    escaped as ``repr`` writes it (``\\n``, ``\\x1b``, ``\\udcff``): a name cannot break a one-line error
    into two, nor send a terminal control sequence."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


class LasagnaError(ValueError):
    """Base class. ``message`` says what was wrong and what was expected; ``where`` is a file, a JSON path
    (``layers[2].blend``) or a tensor name. ``str(error)`` is ``"where: message"`` (or the message alone)."""

    def __init__(self, message: str, where: str | None = None):
        self.message = message
        self.where = where
        super().__init__(printable(f"{where}: {message}" if where else message))

    def at(self, where: str) -> LasagnaError:
        """The same error (same class and message) reported at ``where`` instead."""
        return type(self)(self.message, where)


class DocumentError(LasagnaError):
    """A stack document (``stack.json``) breaks a rule of the format."""


class ImageError(LasagnaError):
    """A PNG (or other raster) is missing, corrupt, too large or of an unsupported kind."""


class PathError(LasagnaError):
    """A path escapes the folder it must stay in, or is not a safe relative path."""


class ExportError(LasagnaError):
    """A document cannot be written in the requested interchange format."""


class ConflictError(LasagnaError):
    """A stack folder changed on disk since it was read: saving would silently overwrite someone's work."""


class ConditionError(LasagnaError):
    """A condition names a label outside a prior's vocabulary, or has the wrong shape."""


# ---- pydantic errors as one line -------------------------------------------------------------------
E = TypeVar("E", bound=LasagnaError)


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
        return format_path(shown), f"got {_short(error.get('input'))}; expected {msg[len('Input should be ') :]}"
    return format_path(shown), f"{msg[:1].lower()}{msg[1:]}; got {_short(error.get('input'))}"


def _meaningful(err: ValidationError) -> list[dict[str, Any]]:
    # A field whose default is computed from other fields reports "not called" when those failed;
    # that is a consequence of the first error, not a second one.
    errors = [e for e in err.errors(include_url=False) if e["type"] != "default_factory_not_called"]
    return errors or err.errors(include_url=False)


def describe_validation_error(
    err: ValidationError,
    where: str | None = None,
    model: type[BaseModel] | None = None,
    error: type[E] = LasagnaError,  # type: ignore[assignment]
    *,
    prefix: str = "",
) -> E:
    """The one-line error for a pydantic ``ValidationError``: ``where: json.path: what; expected … (+N more)``.

    ``where`` names the file (or command); ``prefix`` is the JSON path of the validated object inside it
    (``settings.distill``), put before the first error's own path. Discriminator tags such as ``pixels``
    are dropped from the path (they are not in the file) when ``model``, the class that was validated, is
    given; it also lets the line list the valid keys of an object that received an unknown one.
    ``error`` is the class of the returned error.
    """
    errors = _meaningful(err)
    path, message = _describe(errors[0], model)
    path = ".".join(p for p in (prefix, path) if p)
    more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
    return error(message + more, ": ".join(p for p in (where, path) if p) or None)
