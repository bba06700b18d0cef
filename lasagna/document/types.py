"""Field types shared by the document and preset models: ids, safe paths, unit floats, colours, ranges.

Each type is an ``Annotated`` alias: its validator enforces a rule of docs/ARCHITECTURE.md and
quotes it when it fails, and its JSON Schema states as much of the rule as JSON Schema can.
Numbers are strict (``"0.5"`` and ``true`` are not numbers) and finite: bad input is refused, never
silently coerced.
"""

from __future__ import annotations

import math
import re
import struct
from typing import Annotated

from pydantic import AfterValidator, AllowInfNan, BaseModel, BeforeValidator, ConfigDict, Field, Strict, WithJsonSchema

from lasagna.document.blend import ACCEPTED_BLEND_NAMES, BLEND_MODES, RANGED_BLENDS, BlendMode, canonical_blend
from lasagna.document.validation import RuleError


class StrictModel(BaseModel):
    """Base of every document and preset model: unknown keys refused, frozen, finite floats."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# ---- ids -----------------------------------------------------------------------------------------

ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$"
_ID_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # used with fullmatch: "$" would accept "a\n"

# Windows refuses these as file names even with an extension ("con.png", "aux.mask.png"), so an id
# that is one of them would not be "safe as a file name on every OS" as layers/<id>.png.
WINDOWS_RESERVED: frozenset[str] = frozenset(
    {"CON", "PRN", "AUX", "NUL"} | {f"COM{i}" for i in range(1, 10)} | {f"LPT{i}" for i in range(1, 10)}
)


def _any_case(word: str) -> str:
    return "".join(f"[{c.upper()}{c.lower()}]" if c.isalpha() else c for c in word)


# The same names as a JSON Schema pattern (ECMA-262 regexes have no case-insensitive flag).
_RESERVED_PATTERN = (
    "^("
    + "|".join(_any_case(w) for w in ("con", "prn", "aux", "nul"))
    + f"|({_any_case('com')}|{_any_case('lpt')})[1-9]"
    + r")(\.|$)"
)


def check_id(value: str) -> str:
    """Rule: id matches ^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$ and is not a Windows device name."""
    if not _ID_RE.fullmatch(value):
        raise RuleError(
            f"id {value!r} breaks the rule: ids match {ID_PATTERN} "
            "(a letter or digit, then up to 63 letters, digits, '_', '.', '-')"
        )
    if value.split(".")[0].upper() in WINDOWS_RESERVED:
        raise RuleError(f"id {value!r} is a reserved device name on Windows; ids must be safe file names on every OS")
    return value


_NOT_ID_CHARS = re.compile(r"[^A-Za-z0-9_.-]")
_ID_MAX = 64
_ID_BASE = 56  # leaves room for a reserved stem's "_" and a "-N" suffix within _ID_MAX


def unique_id(name: str, taken: set[str]) -> str:
    """An id made from ``name`` that passes ``check_id`` and whose casefold is not in ``taken`` (then added).

    Characters an id cannot hold become ``-``; a stem that is a Windows device name gets ``_`` appended
    (``aux.png`` → ``aux_.png``); a clash gets ``-2``, ``-3``, … on the stem, before the first dot
    (``a.png`` → ``a-2.png``: after it, a reserved stem would never change). Candidates differ in that
    number, so at most ``len(taken) + 1`` are tried."""
    base = _NOT_ID_CHARS.sub("-", name).lstrip("_.-")[:_ID_BASE] or "layer"
    stem, dot, rest = base.partition(".")
    if stem.upper() in WINDOWS_RESERVED:
        stem += "_"
    n = 1
    while True:
        suffix = f"-{n}" if n > 1 else ""
        candidate = (stem + suffix + dot + rest)[:_ID_MAX]  # stem ≤ 57 characters: only the extension is cut
        if candidate.casefold() not in taken:
            taken.add(candidate.casefold())
            return check_id(candidate)
        n += 1


LayerId = Annotated[
    str,
    Strict(),
    AfterValidator(check_id),
    WithJsonSchema({"type": "string", "pattern": ID_PATTERN, "not": {"pattern": _RESERVED_PATTERN}}),
]

# ---- names -----------------------------------------------------------------------------------------

# What a display name may not hold: control characters (C0, DEL, C1), UTF-16 surrogates (no UTF-8 or UTF-16
# form) and the non-characters U+FFFE, U+FFFF. XML 1.0 (OpenRaster's stack.xml) cannot hold most of them and
# paint programs refuse the rest, so a name the document allows, every writer can write and read back.
_NOT_NAME_CHARS = re.compile("[\x00-\x1f\x7f-\x9f\ud800-\udfff\ufffe\uffff]")
NAME_PATTERN = "^[^\\u0000-\\u001f\\u007f-\\u009f\\ufffe\\uffff]+$"  # JSON Schema's part of the rule
NAME_REPLACEMENT = "\ufffd"  # what importers put in place of each such character (Unicode's replacement)


def check_name(value: str) -> str:
    """Rule: a name is non-empty text without control characters (U+0000–U+001F, U+007F–U+009F), surrogates
    or U+FFFE/U+FFFF."""
    if not value:
        raise RuleError("empty name; names are at least 1 character")
    bad = _NOT_NAME_CHARS.search(value)
    if bad is not None:
        raise RuleError(
            f"name {value[:40]!r} holds {bad.group()!r} at {bad.start()}; names hold no control characters "
            "(U+0000-U+001F, U+007F-U+009F), surrogates or U+FFFE/U+FFFF"
        )
    return value


def sanitise_name(value: str) -> str:
    """``value`` with each character ``check_name`` refuses replaced by U+FFFD (importers, with a warning)."""
    return _NOT_NAME_CHARS.sub(NAME_REPLACEMENT, value)


LayerName = Annotated[
    str,
    Strict(),
    AfterValidator(check_name),
    WithJsonSchema({"type": "string", "minLength": 1, "pattern": NAME_PATTERN}),
]

# ---- safe relative paths --------------------------------------------------------------------------

# What JSON Schema can say about a safe path: not absolute, no drive letter, no backslash or control
# character, no empty segment, no leading "..". (A ".." deeper in the path is checked by the model.)
PATH_PATTERN = r"^(?!/)(?![A-Za-z]:)(?!\.\.(/|$))(?!.*//)(?!.*/$)[^\\\x00-\x1f]+$"
_DRIVE_RE = re.compile(r"[A-Za-z]:")


def check_relative_path(value: str) -> str:
    """Rule: a relative POSIX path inside the stack folder (no absolute path, drive letter,
    backslash, empty segment or '..' that escapes). Returns ``value`` unchanged."""
    rule = "paths are relative POSIX paths inside the stack folder"
    if not value:
        raise RuleError(f"empty path; {rule}")
    if any(ord(c) < 0x20 or c == "\x7f" for c in value):
        raise RuleError(f"path {value!r} contains a control character; {rule}")
    if "\\" in value:
        raise RuleError(f"path {value!r} contains a backslash; {rule}, separated by '/'")
    if value.startswith("/"):
        raise RuleError(f"path {value!r} is absolute; {rule}")
    if _DRIVE_RE.match(value):
        raise RuleError(f"path {value!r} starts with a drive letter; {rule}")
    depth = 0
    for segment in value.split("/"):
        if segment == "":
            raise RuleError(f"path {value!r} has an empty segment ('//' or a trailing '/'); {rule}")
        if segment == "..":
            depth -= 1
            if depth < 0:
                raise RuleError(f"path {value!r} escapes the stack folder with '..'; {rule}")
        elif segment != ".":
            depth += 1
    if depth == 0:
        raise RuleError(f"path {value!r} names the stack folder itself, not a file inside it; {rule}")
    return value


RelativePath = Annotated[
    str,
    Strict(),
    AfterValidator(check_relative_path),
    WithJsonSchema({"type": "string", "pattern": PATH_PATTERN}),
]


def check_name_or_path(value: str) -> str:
    """Rule: a reference is a name (the id rule) or, if it contains '/', a safe relative path."""
    return check_relative_path(value) if "/" in value else check_id(value)


NameOrPath = Annotated[
    str,
    Strict(),
    AfterValidator(check_name_or_path),
    WithJsonSchema(
        {
            "anyOf": [
                {"type": "string", "pattern": ID_PATTERN, "not": {"pattern": _RESERVED_PATTERN}},
                {"type": "string", "pattern": "/", "allOf": [{"pattern": PATH_PATTERN}]},
            ]
        }
    ),
]

_SHA256_RE = re.compile(r"[0-9a-f]{64}")


def check_sha256(value: str) -> str:
    """Rule: a SHA-256 digest is 64 lower-case hex digits."""
    if not _SHA256_RE.fullmatch(value):
        raise RuleError(f"{value!r} is not a SHA-256 digest; expected 64 lower-case hex digits")
    return value


Sha256 = Annotated[
    str, Strict(), AfterValidator(check_sha256), WithJsonSchema({"type": "string", "pattern": "^[0-9a-f]{64}$"})
]

# ---- numbers and colours ----------------------------------------------------------------------------

FiniteFloat = Annotated[float, Strict(), AllowInfNan(False)]
Unit = Annotated[float, Strict(), AllowInfNan(False), Field(ge=0.0, le=1.0)]
Pixels = Annotated[int, Strict(), Field(ge=1, le=32768)]

# An offset must fit the signed 32-bit integers PSD and OpenRaster store layer positions in.
INT32_MAX = 2**31 - 1
Coordinate = Annotated[int, Strict(), Field(ge=-INT32_MAX, le=INT32_MAX)]

Colour = Annotated[tuple[Unit, ...], Field(min_length=3, max_length=4)]
OpaqueColour = tuple[Unit, Unit, Unit]


# Layer values are float32 tensors y = lo + (hi − lo)·v of 16-bit codes v. Both ends and the span hi − lo must
# be finite float32 numbers (beyond FLOAT32_MAX a value is infinite, and v = (y − lo)/(hi − lo) is NaN), and
# one 16-bit step of the span, (hi − lo)/65535, a normal float32 (≥ FLOAT32_TINY): a smaller span flushes
# to a subnormal or to 0 and the stored codes are lost (0/0 again). The spans of real layers (1 for colour,
# 2 for shading, 1e4 for light) are far inside both bounds.
FLOAT32_MAX = 3.4028234663852886e38
FLOAT32_TINY = 1.1754943508222875e-38
MIN_RANGE_SPAN = 65535 * FLOAT32_TINY


def _float32(x: float) -> float:
    """``x`` rounded to float32 (``inf`` beyond its largest finite value)."""
    try:
        return struct.unpack("f", struct.pack("f", x))[0]
    except OverflowError:
        return math.copysign(math.inf, x)


def range_problem(lo: float, hi: float) -> str | None:
    """The range rule, stated once (the document's validator, the compositor's layer specs and the editor
    use it): what [lo, hi] breaks, or None. Rule: finite, lo < hi, both ends and the span hi − lo finite in
    float32, and the span at least ``MIN_RANGE_SPAN`` (one 16-bit step a normal float32)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return f"range [{lo}, {hi}] breaks the rule: both ends finite"
    if not lo < hi:
        return f"range [{lo}, {hi}] breaks the rule lo < hi"
    span = _float32(_float32(hi) - _float32(lo))
    if not (abs(_float32(lo)) <= FLOAT32_MAX and abs(_float32(hi)) <= FLOAT32_MAX and span <= FLOAT32_MAX):
        return (
            f"range [{lo:g}, {hi:g}] breaks the rule: both ends and the span hi - lo within float32's "
            f"±{FLOAT32_MAX:.4g} (layer values are float32)"
        )
    if span < MIN_RANGE_SPAN:
        return (
            f"range [{lo:g}, {hi:g}] breaks the rule: a span hi - lo of at least {MIN_RANGE_SPAN:.3g} "
            "(one 16-bit step of it a normal float32; layer values are float32)"
        )
    return None


def check_range(value: tuple[float, float]) -> tuple[float, float]:
    """Rule: ``range_problem`` (finiteness is checked by the item type first)."""
    problem = range_problem(*value)
    if problem is not None:
        raise RuleError(problem)
    return value


Range = Annotated[tuple[FiniteFloat, FiniteFloat], AfterValidator(check_range)]
UNIT_RANGE: tuple[float, float] = (0.0, 1.0)


def check_range_for_blend(range_: tuple[float, float], blend: str) -> None:
    """Rule: a range other than [0, 1] is allowed only for multiply and plus."""
    if tuple(range_) != UNIT_RANGE and blend not in RANGED_BLENDS:
        raise RuleError(
            f"range [{range_[0]}, {range_[1]}] with blend {blend!r} breaks the rule: a range other "
            f"than [0, 1] is allowed only for {' and '.join(sorted(RANGED_BLENDS))}",
            loc=("range",),
        )


# JSON Schema form of check_range_for_blend, for objects with "blend" and "range" (default normal).
RANGE_FOR_BLEND_SCHEMA = {
    "if": {
        "properties": {"blend": {"enum": [b for b in ACCEPTED_BLEND_NAMES if canonical_blend(b) not in RANGED_BLENDS]}}
    },
    "then": {"properties": {"range": {"const": list(UNIT_RANGE)}}},
}

# ---- blend -------------------------------------------------------------------------------------------

Blend = Annotated[
    BlendMode,
    BeforeValidator(canonical_blend),
    WithJsonSchema(
        {
            "type": "string",
            "enum": list(ACCEPTED_BLEND_NAMES),
            "description": f"Blend mode, one of {', '.join(BLEND_MODES)}; the aliases alpha-linear, "
            "multiply-luminosity and additive are accepted and written canonical.",
        }
    ),
]
