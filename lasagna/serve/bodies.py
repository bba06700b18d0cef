"""The editor's request bodies, checked in one place before any session method runs.

``parse_request_json`` reads a body as ``lasagna.document.validation.parse_json`` reads a stack.json (nesting
depth, integer digits and infinities bounded before the parser can exhaust itself); ``parse_body`` validates
the object against a strict pydantic model: ``"0.5"`` and ``true`` are not numbers, a string is not a list,
unknown keys are refused. Every failure is a ``RequestError`` (HTTP 400) of one line naming the field, what
it expected and what it was given.

One model per ``/api/change`` op, gathered in the table ``CHANGES`` (keyed by the tag ``op``); each model's
``call`` is the one session verb it stands for, so adding an op is adding a model.
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, PlainValidator, ValidationError

from lasagna.document.condition import MAX_SHININESS, parse_direction, parse_surface_light
from lasagna.document.models import MAX_EXTRA_LIGHTS, MAX_RELIEF, ExtraLight, LightIntensity, parses
from lasagna.document.types import Blend, Colour, OpaqueColour
from lasagna.document.validation import parse_json
from lasagna.errors import DocumentError, LasagnaError, describe_validation_error
from lasagna.request import MAX_WITHIN

MAX_TEXT = 1024
"""Longest name, id, preset or condition a request may carry (the document's ids are at most 64 characters;
a display name is free text, but a page never needs kilobytes of it)."""


def _version(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"got {_shown(value)}; expected the integer version the change was made against")
    return value


Version = Annotated[int, PlainValidator(_version)]
Text = Annotated[str, Field(strict=True, max_length=MAX_TEXT)]
Count = Annotated[int, Field(strict=True)]
Light = Annotated[str, Field(strict=True, max_length=MAX_TEXT), AfterValidator(parses(parse_direction, ValueError))]
"""A light as the document writes it: a named light or ``az=A,el=E`` (``parse_direction``), kept as given."""
SurfaceLight = Annotated[
    str, Field(strict=True, max_length=MAX_TEXT), AfterValidator(parses(parse_surface_light, ValueError))
]
"""A surface layer's light: a `Light` or a point light ``x=X,y=Y,z=Z`` (``parse_surface_light``)."""
Ambient = Annotated[float, Field(strict=True, ge=0.0, lt=1.0)]
Relief = Annotated[float, Field(strict=True, gt=0.0, le=MAX_RELIEF, allow_inf_nan=False)]
Share = Annotated[float, Field(strict=True, ge=0.0, le=1.0, allow_inf_nan=False)]
"""A share in [0, 1]: a surface layer's gloss, shadows or occlusion strength."""
Shininess = Annotated[float, Field(strict=True, ge=1.0, le=MAX_SHININESS, allow_inf_nan=False)]
Within = Annotated[float, Field(strict=True, gt=0.0, le=MAX_WITHIN, allow_inf_nan=False)]


class RequestError(LasagnaError):
    """A request that is malformed in itself (not JSON, a missing field, a wrong type): HTTP 400."""


class _Body(BaseModel):
    # Strictness is per field (``Version``, ``Text``, ``Count``, the document's ``Colour``): a model-wide strict
    # mode would also refuse a JSON array where a tuple is declared.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class SetLayer(_Body):
    """Change document fields of a layer (the session checks which fields and their values)."""

    op: Literal["set"]
    version: Version
    id: Text
    changes: dict[str, Any]  # which fields, and their values, the session checks (LAYER_FIELDS)

    def call(self, session):
        return session.set_layer(self.version, self.id, self.changes)


class MoveLayer(_Body):
    op: Literal["move"]
    version: Version
    id: Text
    index: Count

    def call(self, session):
        return session.move_layer(self.version, self.id, self.index)


class DeleteLayer(_Body):
    op: Literal["delete"]
    version: Version
    id: Text

    def call(self, session):
        return session.delete_layer(self.version, self.id)


class GroupLayers(_Body):
    """Wrap sibling layers into a new group (``EditSession.group_layers``)."""

    op: Literal["group"]
    version: Version
    ids: list[Text] = Field(min_length=1)
    name: Text | None = None

    def call(self, session):
        return session.group_layers(self.version, list(self.ids), self.name)


class Ungroup(_Body):
    op: Literal["ungroup"]
    version: Version
    id: Text

    def call(self, session):
        return session.ungroup(self.version, self.id)


class AddSolid(_Body):
    op: Literal["solid"]
    version: Version
    color: Colour
    name: Text | None = None
    blend: Blend = "normal"

    def call(self, session):
        return session.add_solid(self.version, list(self.color), self.name, self.blend)


class AddLearned(_Body):
    op: Literal["learned"]
    version: Version
    preset: Text
    condition: Text
    on: Text | None = None
    method: Literal["amortised", "per-image"] = "amortised"
    kind: Literal["free", "surface"] | None = None

    def call(self, session):
        return session.add_learned(self.version, self.preset, self.condition, self.on, self.method, self.kind)


class SetLight(_Body):
    """Re-light a surface layer (``EditSession.set_light``): ``light``, and ``source_light`` (null: plain
    shading), ``ambient``, ``relief``, ``light_color``, ``light_intensity``, ``extra_lights`` (the whole list; ``[]``
    removes them), ``gloss``, ``shininess``, ``shadows``, ``occlusion`` and ``shadow_depth`` when given; an absent
    field keeps the layer's value."""

    op: Literal["light"]
    version: Version
    id: Text
    light: SurfaceLight
    source_light: Light | None = None
    ambient: Ambient | None = None
    relief: Relief | None = None
    light_color: OpaqueColour | None = None
    light_intensity: LightIntensity | None = None
    extra_lights: Annotated[tuple[ExtraLight, ...], Field(max_length=MAX_EXTRA_LIGHTS)] | None = None
    gloss: Share | None = None
    shininess: Shininess | None = None
    shadows: Share | None = None
    occlusion: Share | None = None
    shadow_depth: Relief | None = None

    def call(self, session):
        keep = "source_light" not in self.model_fields_set  # absent keeps it; null removes it
        source = ... if keep else self.source_light
        return session.set_light(
            self.version,
            self.id,
            self.light,
            source_light=source,
            ambient=self.ambient,
            relief=self.relief,
            light_color=self.light_color,
            light_intensity=self.light_intensity,
            extra_lights=self.extra_lights,
            gloss=self.gloss,
            shininess=self.shininess,
            shadows=self.shadows,
            occlusion=self.occlusion,
            shadow_depth=self.shadow_depth,
        )


class Reread(_Body):
    """Read a relight surface layer again told its source light (``EditSession.reread_surface``); ``within`` (degrees)
    says that light is a rough reading, its elevation fused with the estimator's fit (``lasagna light --within``)."""

    op: Literal["reread"]
    version: Version
    id: Text
    within: Within | None = None

    def call(self, session):
        return session.reread_surface(self.version, self.id, within=self.within)


class Undo(_Body):
    op: Literal["undo"]
    version: Version

    def call(self, session):
        return session.undo(self.version)


class Redo(_Body):
    op: Literal["redo"]
    version: Version

    def call(self, session):
        return session.redo(self.version)


class Save(_Body):
    op: Literal["save"]
    version: Version

    def call(self, session):
        return session.save(self.version)


CHANGES: dict[str, type[_Body]] = {
    "set": SetLayer,
    "move": MoveLayer,
    "delete": DeleteLayer,
    "group": GroupLayers,
    "ungroup": Ungroup,
    "solid": AddSolid,
    "learned": AddLearned,
    "light": SetLight,
    "reread": Reread,
    "undo": Undo,
    "redo": Redo,
    "save": Save,
}
"""The ``/api/change`` ops, each the model of its body (tag ``op``)."""


class StartJob(_Body):
    version: Version
    kind: Text  # refine or rerender: the session says so when it is neither
    id: Text
    steps: Count | None = None


class Empty(_Body):
    """The body of a POST that carries nothing (reload, cancel): ``{}`` or no body."""


def parse_request_json(data: bytes) -> dict[str, Any]:
    """The JSON object of a request body (empty: ``{}``), bounded as a stack.json is (``parse_json``)."""
    if not data:
        return {}
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise RequestError(f"the body is not UTF-8 (byte {exc.start}); expected a JSON object", "body") from None
    try:
        value = parse_json(text, "body")
    except DocumentError as exc:
        message = exc.message
        if message.startswith("invalid JSON"):  # parse_json's syntax line points at the stack.json schema
            message = f"the body is not JSON ({message.split('; expected')[0]}); expected a JSON object"
        raise RequestError(message, "body") from None
    if not isinstance(value, dict):
        raise RequestError(f"the body is a JSON {_json_type(value)}; expected a JSON object", "body")
    return value


def parse_body(model: type[BaseModel], value: dict[str, Any]) -> Any:
    """``value`` validated as ``model``; a ``RequestError`` naming the first field at fault."""
    try:
        return model.model_validate(value)
    except ValidationError as err:
        exc = describe_validation_error(err, None, model, RequestError)
        message = exc.message
        for python, js in _JSON_WORDS.items():
            message = message.replace(python, js)
        raise RequestError(message, exc.where) from None


# pydantic names Python types; a request is JSON.
_JSON_WORDS = {"a valid tuple": "a JSON array", "a valid list": "a JSON array", "a valid dictionary": "a JSON object"}


def parse_change(value: dict[str, Any]) -> Any:
    """An ``/api/change`` body as the model its ``op`` names."""
    if "op" not in value:
        raise RequestError(f"missing field 'op'; expected one of {', '.join(CHANGES)}", "body")
    op = value["op"]
    if not isinstance(op, str) or op not in CHANGES:
        raise RequestError(f"unknown op {_shown(op)}; expected one of {', '.join(CHANGES)}", "op")
    return parse_body(CHANGES[op], value)


def _json_type(value: Any) -> str:
    names = {dict: "object", list: "array", str: "string", bool: "boolean", int: "number", float: "number"}
    return "null" if value is None else names.get(type(value), type(value).__name__)


def _shown(value: Any) -> str:
    """A given value as the error line quotes it: JSON, cut short."""
    text = json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


__all__ = ["CHANGES", "Empty", "RequestError", "StartJob", "parse_body", "parse_change", "parse_request_json"]
