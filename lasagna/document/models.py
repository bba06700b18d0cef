"""The stack document (``stack.json``, format ``lasagna.stack`` version 1) as pydantic v2 models.

One model per layer kind, each with ``kind: Literal[...]``, gathered in the discriminated union
``Layer`` (the geojson-pydantic pattern). Every rule of docs/ARCHITECTURE.md ("The stack folder and
stack.json") is a validator whose message quotes the rule. Models are frozen: change a document
with the ``with_*``/``replace*`` helpers, which return a new, re-validated document.

Serialisation choice: ``to_json`` writes *explicit, full* documents (every field, defaults
included, in declaration order, 2-space indent, short number arrays on one line), so a reader of
a stack.json sees every setting that affects the render without knowing the defaults, and the
output of a canonical document is byte-for-byte stable. The one exception is ``clip``, written only
when true, so that stacks without clipping masks keep their bytes.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from typing import Annotated, Any, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    JsonValue,
    SerializerFunctionWrapHandler,
    Strict,
    ValidationError,
    WithJsonSchema,
    model_serializer,
    model_validator,
)

from lasagna.document.adjustment import Adjustment
from lasagna.document.condition import (
    AMBIENT,
    DEFAULT_SHININESS,
    DIRECTION_PATTERN,
    MAX_SHININESS,
    POINT_PATTERN,
    parse_direction,
    parse_surface_light,
)
from lasagna.document.gradient import GradientFill
from lasagna.document.pattern import PatternFill
from lasagna.document.types import (
    RANGE_FOR_BLEND_SCHEMA,
    UNIT_RANGE,
    Blend,
    Colour,
    Coordinate,
    LayerId,
    LayerName,
    NameOrPath,
    OpaqueColour,
    Pixels,
    Range,
    RelativePath,
    Sha256,
    StrictModel,
    Unit,
    check_range_for_blend,
)
from lasagna.document.validation import RuleError, check_serialised, document_error, parse_json
from lasagna.errors import ConditionError, DocumentError
from lasagna.limits import MAX_GROUP_DEPTH

FORMAT = "lasagna.stack"
VERSION = 1


class Canvas(StrictModel):
    """The output image: its size and what the composite starts from — an opaque colour, or nothing (a transparent
    document, whose composite carries alpha)."""

    width: Pixels = Field(description="Width in pixels, an integer in [1, 32768].")
    height: Pixels = Field(description="Height in pixels, an integer in [1, 32768].")
    background: OpaqueColour | None = Field(
        (0.0, 0.0, 0.0),
        description="Opaque RGB background in [0, 1]; every blend composes over it. null: no background (a "
        "transparent document): the layers are composited onto transparency, as an isolated group's are, and the "
        "composite carries alpha (an RGBA PNG).",
    )


class Offset(StrictModel):
    """Position of a layer's top-left corner on the canvas; may be negative or off-canvas."""

    x: Coordinate = Field(0, description="Pixels to the right of the canvas's left edge.")
    y: Coordinate = Field(0, description="Pixels below the canvas's top edge.")


class Size(StrictModel):
    """Size of a solid, gradient or pattern layer's rectangle."""

    width: Pixels = Field(description="Width in pixels, an integer in [1, 32768].")
    height: Pixels = Field(description="Height in pixels, an integer in [1, 32768].")


class Condition(StrictModel):
    """What a learned layer is asked for: a label of its preset's vocabulary, optionally a prompt (free text for
    a text-conditioned prior: the label then only names it) and a negative prompt."""

    label: str = Field(min_length=1, description="A label of the preset's condition vocabulary, e.g. 'left'.")
    prompt: str | None = Field(
        None, min_length=1, description="Free-text prompt replacing the preset's template (text-conditioned priors)."
    )
    negative_prompt: str | None = Field(
        None,
        min_length=1,
        description="Text replacing the unconditional branch of classifier-free guidance (text-conditioned priors).",
    )


class GeneratorRef(StrictModel):
    """The weights that produce a learned layer."""

    checkpoint: RelativePath = Field(description="Relative POSIX path of the generator's safetensors file.")
    sha256: Sha256 | None = Field(None, description="Lower-case hex SHA-256 of the checkpoint, checked on load.")
    config_sha256: Sha256 | None = Field(
        None,
        description="Lower-case hex SHA-256 of the config.json beside the checkpoint (its vocabulary maps labels "
        "to the weights' inputs), checked on load.",
    )


def _layer_schema(schema: dict[str, Any]) -> None:
    # ``kind`` has a default for Python callers (PixelsLayer(id=..., source=...)), but a file must
    # state it: it selects the union member, and pydantic refuses a layer without it.
    schema["required"] = ["kind", *(r for r in schema.get("required", []) if r != "kind")]
    schema.update(RANGE_FOR_BLEND_SCHEMA)


class _Common(StrictModel):
    """Fields every layer kind shares, groups included (listed bottom to top in ``Document.layers``)."""

    model_config = ConfigDict(json_schema_extra=_layer_schema)

    id: LayerId = Field(description="Unique (case-insensitively, in the whole tree) id, safe as a file name.")
    name: LayerName = Field(
        default_factory=lambda data: data["id"],
        description="Display name, without control characters; defaults to the id.",
    )
    kind: str  # each kind redeclares it as a Literal tag; declared here so it is written third
    blend: Blend = Field("normal", description="How the layer composes onto what lies below it.")
    opacity: Unit = Field(1.0, description="Opacity in [0, 1]; alpha_effective = alpha * mask * opacity.")
    visible: bool = Field(True, strict=True, description="Hidden layers are kept but not composed.")
    offset: Offset = Field(Offset(), description="Top-left corner on the canvas, integer pixels.")
    clip: bool = Field(
        False,
        strict=True,
        description="Clipped to the layer below (Photoshop's clipping mask): shown only where the chain's base — the "
        "nearest layer below in the same list that is not clipped — has alpha; the base's blend and opacity apply to "
        "the chain as one.",
    )

    @model_serializer(mode="wrap")
    def _clip_written_when_set(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        # The one field written only when set: a stack without clipping masks keeps the bytes it had before
        # clipping existed (the module doc's "every field" otherwise holds).
        data = handler(self)
        if not self.clip:
            data.pop("clip", None)
        return data


class _LayerBase(_Common):
    """Fields every raster kind shares (pixels, solid, learned): a value range and a mask of its size."""

    range: Range = Field(
        UNIT_RANGE,
        description="[lo, hi], lo < hi: stored values v in [0, 1] mean y = lo + (hi - lo) * v (alpha is never "
        "mapped). Only multiply and plus may use a range other than [0, 1].",
    )
    mask: RelativePath | None = Field(None, description="Gray PNG the size of the layer, multiplied into its alpha.")

    @model_validator(mode="after")
    def _range_allowed_for_blend(self) -> _LayerBase:
        check_range_for_blend(self.range, self.blend)
        return self


class PixelsLayer(_LayerBase):
    """A layer whose pixels are a PNG in the stack folder."""

    kind: Literal["pixels"] = Field("pixels", description="Layer kind: pixels from a PNG.")
    source: RelativePath = Field(description="The layer's PNG, e.g. layers/<id>.png.")


class SolidLayer(_LayerBase):
    """A rectangle of one colour. Its RGB is mapped by ``range`` exactly as a PNG's values are."""

    kind: Literal["solid"] = Field("solid", description="Layer kind: one colour.")
    color: Colour = Field(description="RGB or RGBA floats in [0, 1] (alpha multiplies opacity).")
    size: Size | None = Field(None, description="Rectangle size; null means the canvas size.")


class GradientLayer(_Common):
    """A gradient fill (Photoshop's gradient fill layer): a ramp through colour and opacity stops over a rectangle.

    ``gradient`` holds the ramp and its stops (``lasagna.document.gradient``); ``lasagna.compose.gradient`` renders
    them as psd-tools' ``draw_gradient_fill`` does, relative to the layer's rectangle (``gradient.align``) or the
    canvas. Its colour is a colour (the unit range); opacity stops are its alpha.
    """

    kind: Literal["gradient"] = Field("gradient", description="Layer kind: a gradient fill.")
    gradient: GradientFill = Field(description="The ramp (style, angle, scale, …) and its colour and opacity stops.")
    size: Size | None = Field(None, description="Rectangle size; null means the canvas size.")
    mask: RelativePath | None = Field(None, description="Gray PNG the size of the layer, multiplied into its alpha.")

    @property
    def range(self) -> tuple[float, float]:
        """A gradient's colour is a colour: the unit range."""
        return UNIT_RANGE


class PatternLayer(_Common):
    """A pattern fill (Photoshop's pattern fill layer): a tile repeated over a rectangle.

    ``source`` is the tile (RGB or RGBA PNG, 8 or 16 bits); ``pattern`` its scale, phase and alignment
    (``lasagna.document.pattern``); ``lasagna.compose.pattern`` tiles it over the layer's rectangle from the
    rectangle's corner (``pattern.align``) or the canvas's, as psd-tools' ``draw_pattern_fill`` does. Its colour is a
    colour (the unit range); the tile's alpha is its alpha.
    """

    kind: Literal["pattern"] = Field("pattern", description="Layer kind: a pattern fill.")
    source: RelativePath = Field(description="The tile: an RGB or RGBA PNG (8 or 16 bits), e.g. layers/<id>.png.")
    pattern: PatternFill = Field(PatternFill(), description="How the tile is laid: scale, phase, align.")
    size: Size | None = Field(None, description="Rectangle size; null means the canvas size.")
    mask: RelativePath | None = Field(None, description="Gray PNG the size of the layer, multiplied into its alpha.")

    @property
    def range(self) -> tuple[float, float]:
        """A pattern's colour is a colour: the unit range."""
        return UNIT_RANGE


class LearnedLayer(_LayerBase):
    """A layer produced by a generator from the layer it is conditioned on (Lasagna, Sec. 3)."""

    kind: Literal["learned"] = Field("learned", description="Layer kind: produced by a learned generator.")
    preset: NameOrPath = Field(
        description="A preset name (layers/<name>/preset.json in the stack folder or the catalogue) or, "
        "if it contains '/', a relative path to a preset.json inside the stack folder.",
    )
    condition: Condition = Field(description="The label (and optional prompt) the layer is generated for.")
    conditioned_on: LayerId = Field(description="Id of a layer below this one, the generator's input.")
    source: RelativePath | None = Field(None, description="Rendered pixels, stored exactly as a pixels layer's.")
    generator: GeneratorRef | None = Field(None, description="The generator's checkpoint, if trained.")
    settings: dict[str, JsonValue] = Field(
        default_factory=dict, description="Free-form generator/distillation settings."
    )


def parses(parse: Callable[[str], object], error: type[Exception] = RuleError) -> Callable[[str], str]:
    """A validator of a light's text: read by ``parse`` and kept as given; its `ConditionError` (which says what a
    light is) raised again as ``error`` — a `RuleError` the model reports at the field, or the ``ValueError`` a
    request body's model wants."""

    def rule(value: str) -> str:
        try:
            parse(value)
        except ConditionError as exc:
            raise error(exc.message) from None
        return value

    return rule


LightText = Annotated[
    str,
    Strict(),
    AfterValidator(parses(parse_direction)),  # a named direction or az=A,el=E in degrees, el in [0, 90)
    WithJsonSchema(
        {
            "type": "string",
            "pattern": DIRECTION_PATTERN,
            "description": "A named light (left, top-right, …) or 'az=A,el=E' in degrees, el in [0, 90).",
        }
    ),
]


def _surface_schema(schema: dict[str, Any]) -> None:
    schema["required"] = ["kind", *(r for r in schema.get("required", []) if r != "kind")]
    # JSON Schema form of SurfaceLayer._multiplies: blend multiply; a relight ratio needs ambient > 0.
    schema["properties"]["blend"] = {"enum": ["multiply", "multiply-luminosity"], "default": "multiply"}
    schema["if"] = {"required": ["source_light"], "properties": {"source_light": {"type": "string"}}}
    schema["then"] = {"properties": {"ambient": {"exclusiveMinimum": 0}}}


WHITE_LIGHT = (1.0, 1.0, 1.0)
"""A surface layer's default light colour: the multiplier is one channel, the same on R, G and B."""
MAX_LIGHT_INTENSITY = 8.0
"""The largest intensity a surface layer's light takes: ×8 turns the ambient floor 0.25 into a peak of 6.25."""
LightIntensity = Annotated[float, Field(strict=True, gt=0.0, le=MAX_LIGHT_INTENSITY, allow_inf_nan=False)]
"""A light's intensity k, in (0, MAX_LIGHT_INTENSITY]: its direct term times k."""
MAX_RELIEF = 16.0
"""The largest relief gain a surface layer takes: slopes ×16 turn a 5° bump into a 54° one; beyond it every
relief is a cliff and the map's 16-bit quantisation (slopes to 3e-5) starts to show."""


SurfaceLightText = Annotated[
    str,
    Strict(),
    AfterValidator(parses(parse_surface_light)),  # a direction (as LightText) or a point light x=X,y=Y,z=Z
    WithJsonSchema(
        {
            "type": "string",
            "anyOf": [{"pattern": DIRECTION_PATTERN}, {"pattern": POINT_PATTERN}],
            "description": "A named light (left, top-right, …), 'az=A,el=E' in degrees (el in [0, 90)), or a point "
            "light 'x=X,y=Y,z=Z': x, y fractions of the layer's width and height from its top-left, z its height in "
            "units of the layer's longer side.",
        }
    ),
]


MAX_EXTRA_LIGHTS = 8
"""The most lights a surface layer takes besides its own ``light`` (Photoshop's Lighting Effects takes 16 in all)."""


class ExtraLight(StrictModel):
    """One more light on a surface layer (Lighting Effects' several lights): its direct term is added to the layer's
    own light's, a + (1 − a)·Σ kᵢ·cᵢ·fᵢ·max(0, n·lᵢ) (fᵢ a point light's falloff, 1 for a direction)."""

    light: SurfaceLightText = Field(description="A named light, 'az=A,el=E', or a point light 'x=X,y=Y,z=Z'.")
    color: OpaqueColour = Field(WHITE_LIGHT, description="Its colour, RGB in [0, 1] (its direct term times it).")
    intensity: LightIntensity = Field(1.0, description="Its intensity (its direct term times it).")


def _share(description: str) -> Any:
    """A surface layer's strength in [0, 1] — its gloss, shadows or occlusion — 0 (off, the world's contract) by
    default."""
    return Field(0.0, strict=True, ge=0.0, le=1.0, allow_inf_nan=False, description=description)


class SurfaceLayer(_Common):
    """A surface — a tangent-space normal map — rendered to a luminosity multiplier under its light.

    The multiplier is Lambert with ambient, the world's contract (`lasagna.compose.surface`): the shading
    S(light) = a + (1 − a)·max(0, n·l) or, with ``source_light``, the relight ratio S(light)/S(source_light)
    that turns an image lit from ``source_light`` into one lit from ``light``, of the map's normals with their
    relief times ``relief``. Editing ``light`` or ``relief`` in stack.json re-renders the layer exactly, with no
    learning. Its blend is multiply: the multiplier scales the colour below it, so the paint under it is kept.
    """

    model_config = ConfigDict(json_schema_extra=_surface_schema)

    kind: Literal["surface"] = Field("surface", description="Layer kind: a normal map lit by a directional light.")
    source: RelativePath = Field(
        description="The normal map: a 16-bit RGB PNG, tangent space, n ↦ (n + 1)/2 with +Y up (the OpenGL "
        "convention of Blender, Krita and Godot)."
    )
    light: SurfaceLightText = Field(
        description="The light it is rendered under: a named light, 'az=A,el=E', or a point light 'x=X,y=Y,z=Z' "
        "(inverse-square falloff, 1 directly beneath it)."
    )
    source_light: LightText | None = Field(
        None, description="If set, the layer is the relight ratio S(light)/S(source_light) of the surface."
    )
    ambient: float = Field(
        AMBIENT, ge=0.0, lt=1.0, allow_inf_nan=False, description="Ambient term a of a + (1 − a)·max(0, n·l)."
    )
    relief: float = Field(
        1.0,
        strict=True,
        gt=0.0,
        le=MAX_RELIEF,
        allow_inf_nan=False,
        description="Relief gain: the map's slopes times this before it is lit, n ↦ (g·n_x, g·n_y, n_z) "
        "renormalised (glTF's normalTexture.scale; the normals of the height field times g); 1: the map as stored.",
    )
    light_color: OpaqueColour = Field(
        WHITE_LIGHT,
        description="The light's colour, RGB in [0, 1]: each channel's direct term times it, a + (1 − a)·c·max(0, n·l) "
        "(the ambient and a relight's source light stay white); white renders the one-channel multiplier.",
    )
    light_intensity: LightIntensity = Field(
        1.0,
        description="The light's intensity k: the direct term times it, a + (1 − a)·k·c·max(0, n·l) (Photoshop's "
        "Lighting Effects Intensity); above 1 a shading layer brightens where the light falls.",
    )
    extra_lights: tuple[ExtraLight, ...] = Field(
        (),
        max_length=MAX_EXTRA_LIGHTS,
        description="More lights, each added to the layer's own: S = a + (1 − a)·Σ kᵢ·cᵢ·fᵢ·max(0, n·lᵢ) over "
        "``light`` and these (a fill or rim light beside the key); a relight ratio still divides by S(source_light).",
    )
    gloss: float = _share(
        "Highlight strength g: each light's direct term gains g·max(0, n·h)^p where it lights the surface "
        "(Blinn–Phong, h the half vector toward the viewer; Photoshop's Lighting Effects Gloss, Blender's specular); "
        "0: Lambert alone, the world's contract. A relight ratio's source light stays diffuse."
    )
    shininess: float = Field(
        DEFAULT_SHININESS,
        strict=True,
        ge=1.0,
        le=MAX_SHININESS,
        allow_inf_nan=False,
        description="Highlight exponent p: larger is a smaller, sharper highlight (32: half its peak 12° off the half "
        "vector); read only where gloss > 0.",
    )
    shadows: float = _share(
        "Cast-shadow strength s: each light's direct term times 1 − s·(1 − V), V whether the light sees "
        "the pixel over the heights integrated from the normal map (a bump darkens what lies behind it; "
        "`lasagna.compose.shadow`); 0: none, the world's contract. A relight ratio's source light casts none."
    )
    shadow_depth: float = Field(
        1.0,
        strict=True,
        gt=0.0,
        le=MAX_RELIEF,
        allow_inf_nan=False,
        description="The heights shadows and occlusion are traced over, times this: longer shadows and deeper creases "
        "for a map whose slopes hold less height than it has (an object's outline is a step no normal holds); the "
        "shading is unchanged. 1: the heights integrated from the map (its relief applied).",
    )
    occlusion: float = _share(
        "Ambient occlusion strength o: the ambient term a times 1 − o·(1 − A), A the share of the sky "
        "each point of the map's heights sees (creases and the feet of walls get less ambient light; "
        "`lasagna.compose.shadow.occlusion`); 0: none, the world's contract. A relight ratio has it above and below."
    )
    mask: RelativePath | None = Field(None, description="Gray PNG the size of the layer, multiplied into its alpha.")
    made_by: dict[str, JsonValue] = Field(
        default_factory=dict,
        description="How the surface was made (preset, estimator and its SHA-256, the layer it was estimated from, "
        "refinement): a record; the render reads only the map and the light.",
    )

    @property
    def range(self) -> tuple[float, float]:
        """The stored map's codes are read as [0, 1] (a normal map is not range-mapped)."""
        return UNIT_RANGE

    @model_validator(mode="after")
    def _multiplies(self) -> SurfaceLayer:
        if self.blend not in ("multiply", "multiply-luminosity"):
            raise RuleError(
                f"surface layer {self.id!r} has blend {self.blend!r}; a surface renders a luminosity multiplier: "
                "expected blend 'multiply'",
                loc=("blend",),
            )
        if self.source_light is not None and self.ambient <= 0.0:
            raise RuleError(
                f"surface layer {self.id!r} is a relight ratio with ambient 0 (S(source_light) would be 0 where the "
                "source does not reach); expected ambient > 0",
                loc=("ambient",),
            )
        return self


class AdjustmentLayer(_Common):
    """An adjustment layer: a parametric function of what lies below it (Photoshop's adjustment layers).

    Where it applies, the layer's colour is ``f(Cb)``, ``f`` the adjustment of ``adjustment.type``
    (``lasagna.compose.adjust``) of the backdrop Cb, blended with ``blend`` and α = mask × opacity; the alpha
    below is kept (over a backdrop with alpha, inside an isolated group or a clipping chain, only its colour
    changes). It covers the canvas, or with a ``mask`` only the mask's rectangle, its top-left corner at the
    layer's offset (as a group's mask).
    """

    kind: Literal["adjustment"] = Field("adjustment", description="Layer kind: an adjustment of what lies below.")
    adjustment: Adjustment = Field(description="The function and its parameters; ``type`` names it.")
    mask: RelativePath | None = Field(
        None,
        description="Gray PNG whose top-left corner is at the layer's offset; the adjustment applies only inside "
        "it, by its value.",
    )

    @property
    def range(self) -> tuple[float, float]:
        """An adjustment's colour is a colour: the unit range."""
        return UNIT_RANGE


def _group_schema(schema: dict[str, Any]) -> None:
    schema["required"] = ["kind", *(r for r in schema.get("required", []) if r != "kind")]
    # JSON Schema form of _pass_through_blends_normally: isolated absent or false -> blend normal.
    schema.update(
        {
            "if": {"not": {"required": ["isolated"], "properties": {"isolated": {"const": True}}}},
            "then": {"properties": {"blend": {"enum": [PASS_THROUGH_BLEND, *PASS_THROUGH_ALIASES]}}},
        }
    )


# A pass-through group has no blend of its own (Photoshop's "Pass Through" is a blend mode in place of
# the others; Krita ignores the composite op of a pass-through group): its children blend with what
# lies below it. "alpha-linear" is normal's alias.
PASS_THROUGH_BLEND = "normal"
PASS_THROUGH_ALIASES = ("alpha-linear",)


class GroupLayer(_Common):
    """A group of layers composited as one (W3C Compositing and Blending Level 1, section 8 "Compositing Groups").

    ``isolated: true`` — an isolated group (section 8.2): the children are composited onto a fully transparent
    initial backdrop, and the result (colour and alpha) is blended onto the group backdrop with the group's
    ``blend``, alpha × ``mask`` × ``opacity``. ``isolated: false`` (the default, as Photoshop's and Krita's
    "pass through") — the children are composited onto the group backdrop itself, and the group's
    ``mask`` × ``opacity`` α mixes that result with the backdrop, Cb + α(Cn − Cb): a non-isolated group
    whose blend is normal. ``offset`` moves the group's children and its mask.
    """

    model_config = ConfigDict(json_schema_extra=_group_schema)

    kind: Literal["group"] = Field("group", description="Layer kind: a group of layers.")
    mask: RelativePath | None = Field(
        None,
        description="Gray PNG whose top-left corner is at the group's offset; the group shows only inside it "
        "(its effective alpha is multiplied by the mask, 0 outside).",
    )
    isolated: bool = Field(
        False,
        strict=True,
        description="true: composite the children onto a transparent backdrop, then blend the group (W3C "
        "isolated group); false: pass through (children blend with what lies below; blend must be normal).",
    )
    layers: tuple[Layer, ...] = Field((), description="The group's layers, bottom to top (nested groups allowed).")

    @model_validator(mode="after")
    def _pass_through_blends_normally(self) -> GroupLayer:
        if not self.isolated and self.blend != PASS_THROUGH_BLEND:
            raise RuleError(
                f"group {self.id!r} passes through (isolated: false) with blend {self.blend!r}; a pass-through "
                "group has no blend of its own: expected blend 'normal', or isolated: true to blend the group",
                loc=("blend",),
            )
        return self


Layer = Annotated[
    PixelsLayer
    | SolidLayer
    | LearnedLayer
    | SurfaceLayer
    | AdjustmentLayer
    | GroupLayer
    | GradientLayer
    | PatternLayer,
    Field(discriminator="kind"),
]
GroupLayer.model_rebuild()
LAYER_KINDS: tuple[str, ...] = tuple(
    m.model_fields["kind"].default
    for m in (
        PixelsLayer,
        SolidLayer,
        LearnedLayer,
        SurfaceLayer,
        AdjustmentLayer,
        GroupLayer,
        GradientLayer,
        PatternLayer,
    )
)
LayerPath = tuple[str | int, ...]  # JSON path of a layer: ("layers", 2, "layers", 0)


def walk_layers(layers: tuple[Layer, ...], loc: LayerPath = ()) -> Iterator[tuple[LayerPath, Layer]]:
    """Every layer of a tree with its JSON path, depth first, bottom to top, a group before its children."""
    for i, layer in enumerate(layers):
        here = (*loc, "layers", i)
        yield here, layer
        if isinstance(layer, GroupLayer):
            yield from walk_layers(layer.layers, here)


def _layer_lists(layers: tuple[Layer, ...], loc: LayerPath = ()) -> Iterator[tuple[LayerPath, tuple[Layer, ...]]]:
    """Every layer list of a tree (the top-level one, then each group's) with the JSON path of its owner."""
    yield loc, layers
    for i, layer in enumerate(layers):
        if isinstance(layer, GroupLayer):
            yield from _layer_lists(layer.layers, (*loc, "layers", i))


def clip_chains(layers: tuple[Layer, ...]) -> list[tuple[Layer, tuple[Layer, ...]]]:
    """One list's layers as (layer, the layers clipped to it), bottom to top: a clipping chain is a base and the
    run of clipped layers directly above it."""
    out: list[tuple[Layer, list[Layer]]] = []
    for layer in layers:
        if layer.clip and out:
            out[-1][1].append(layer)
        else:
            out.append((layer, []))
    return [(base, tuple(clipped)) for base, clipped in out]


def json_path(loc: LayerPath) -> str:
    """``("layers", 2, "layers", 0, "mask")`` → ``layers[2].layers[0].mask``."""
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
    return out


class Document(StrictModel):
    """A layer stack: the canvas, how to blend, and the layers bottom to top."""

    format: Literal["lasagna.stack"] = Field(description="Always 'lasagna.stack'.")
    version: Literal[1] = Field(description="Format version; this is version 1.")
    canvas: Canvas = Field(description="Output size and background.")
    blend_space: Literal["srgb", "linear"] = Field(
        "srgb", description="'srgb' blends encoded values (GIMP, Krita, Photoshop); 'linear' blends linear light."
    )
    clamp: Literal["layer", "output"] = Field(
        "layer", description="'layer' clamps to [0, 1] after each blend; 'output' clamps once at the end."
    )
    layers: tuple[Layer, ...] = Field(min_length=1, description="Layers, bottom to top.")
    metadata: dict[str, JsonValue] = Field(default_factory=dict, description="Free-form metadata.")

    @model_validator(mode="after")
    def _ids_and_references(self) -> Document:
        seen: dict[str, LayerPath] = {}  # casefolded id -> JSON path, for uniqueness across the tree
        for loc, layer in walk_layers(self.layers):
            key = layer.id.casefold()
            if key in seen:
                raise RuleError(
                    f"id {layer.id!r} repeats {json_path(seen[key])}.id; ids are unique case-insensitively "
                    "across the whole tree, groups included",
                    loc=(*loc, "id"),
                )
            seen[key] = loc
            if isinstance(layer, GroupLayer) and len(loc) // 2 > MAX_GROUP_DEPTH:
                raise RuleError(
                    f"group {layer.id!r} is nested {len(loc) // 2} deep; groups nest at most {MAX_GROUP_DEPTH} "
                    "deep (so that stack.json stays within the JSON depth validate reads)",
                    loc=(*loc, "layers"),
                )
            if isinstance(layer, LearnedLayer) and len(loc) > 2:
                raise RuleError(
                    f"learned layer {layer.id!r} is inside a group; learned layers are top-level (their input, "
                    "the composite up to conditioned_on, is defined on the top-level list)",
                    loc=(*loc, "kind"),
                )
        for loc, layers in _layer_lists(self.layers):
            if layers and layers[0].clip:
                raise RuleError(
                    f"layer {layers[0].id!r} is clipped but is the bottom of its list; a clipped layer clips to the "
                    "layer below it in the same list: expected clip false",
                    loc=(*loc, "layers", 0, "clip"),
                )
        below: set[str] = set()  # exact ids of the top-level layers below the current one
        for i, layer in enumerate(self.layers):
            if isinstance(layer, LearnedLayer) and layer.conditioned_on not in below:
                raise RuleError(
                    f"{layer.conditioned_on!r} is not the id of a layer below {layer.id!r} in the top-level list; "
                    "conditioned_on names a layer below the learned layer (a top-level layer or group)",
                    loc=("layers", i, "conditioned_on"),
                )
            below.add(layer.id)
        return self

    # ---- reading -------------------------------------------------------------------------------

    @property
    def ids(self) -> tuple[str, ...]:
        """Layer ids, bottom to top."""
        return tuple(layer.id for layer in self.layers)

    def index(self, id: str) -> int:
        """Position of layer ``id`` (0 = bottom); ``DocumentError`` naming the ids if absent."""
        for i, layer in enumerate(self.layers):
            if layer.id == id:
                return i
        raise DocumentError(f"no layer with id {id!r}; expected one of {', '.join(self.ids)}", "layers")

    def layer(self, id: str) -> Layer:
        """The layer with id ``id``, at any depth (inside groups too)."""
        for _, layer in walk_layers(self.layers):
            if layer.id == id:
                return layer
        raise DocumentError(f"no layer with id {id!r}; expected one of {', '.join(self.all_ids)}", "layers")

    def walk(self) -> Iterator[tuple[str, Layer]]:
        """Every layer with its JSON path (``layers[2].layers[0]``), depth first, a group before its children."""
        for loc, layer in walk_layers(self.layers):
            yield json_path(loc), layer

    @property
    def all_ids(self) -> tuple[str, ...]:
        """Every layer id of the tree, depth first, a group before its children."""
        return tuple(layer.id for _, layer in walk_layers(self.layers))

    # ---- changing (each returns a new, validated document) ------------------------------------

    def replace(self, **changes: Any) -> Document:
        """A copy with top-level fields changed, e.g. ``doc.replace(blend_space="linear")``."""
        return self._validated({**self.model_dump(), **changes})

    def with_layers(self, layers: list[Layer | dict[str, Any]]) -> Document:
        """A copy whose layer list is ``layers`` (models or plain dicts)."""
        dumped = [layer.model_dump() if isinstance(layer, BaseModel) else layer for layer in layers]
        return self._validated({**self.model_dump(), "layers": dumped})

    def with_layer(self, layer: Layer | dict[str, Any], index: int | None = None) -> Document:
        """Replace the layer with ``layer``'s id in place, or insert it at ``index`` (default: on top)."""
        id = layer.get("id") if isinstance(layer, dict) else layer.id
        layers: list[Layer | dict[str, Any]] = list(self.layers)
        if id in self.ids:
            if index is not None:
                raise DocumentError(f"layer {id!r} already exists; index applies to new layers only", "layers")
            layers[self.index(id)] = layer
        else:
            layers.insert(len(layers) if index is None else index, layer)
        return self.with_layers(layers)  # validates a dict layer with the rest, so errors name layers[i]

    def replace_layer(self, id: str, **changes: Any) -> Document:
        """A copy where layer ``id`` (at any depth) has ``changes`` applied, e.g.
        ``replace_layer("shade", opacity=0.5)``."""
        return self._edit_siblings(id, lambda layers, i: layers.__setitem__(i, {**layers[i], **changes}))

    def relit(
        self,
        id: str,
        light: str,
        *,
        source_light: str | None = ...,  # type: ignore[assignment]
        ambient: float | None = None,
        relief: float | None = None,
        light_color: tuple[float, float, float] | None = None,
        light_intensity: float | None = None,
        extra_lights: Any = None,
        gloss: float | None = None,
        shininess: float | None = None,
        shadows: float | None = None,
        occlusion: float | None = None,
        shadow_depth: float | None = None,
    ) -> Document:
        """A copy where the surface layer ``id`` has a new ``light`` (and ``source_light`` — None for plain shading,
        ``...`` kept — ``ambient``, ``relief``, ``light_color``, ``light_intensity``, ``extra_lights`` (ExtraLight
        models or their dicts, ``()`` none), ``gloss``, ``shininess``, ``shadows``, ``occlusion`` and
        ``shadow_depth``, when given); every value checked by the layer's model. No pixels change."""
        layer = self.layer(id)
        if not isinstance(layer, SurfaceLayer):
            raise DocumentError(f"layer {id!r} is a {layer.kind} layer; expected a surface layer", where="set_light")
        changes: dict[str, Any] = {"light": light}
        if source_light is not ...:
            changes["source_light"] = source_light
        if ambient is not None:
            changes["ambient"] = float(ambient)
        if relief is not None:
            changes["relief"] = float(relief)
        if light_color is not None:
            changes["light_color"] = tuple(float(c) for c in light_color)
        if light_intensity is not None:
            changes["light_intensity"] = light_intensity
        if extra_lights is not None:
            changes["extra_lights"] = tuple(
                e.model_dump() if hasattr(e, "model_dump") else dict(e) for e in extra_lights
            )
        if gloss is not None:
            changes["gloss"] = gloss
        if shininess is not None:
            changes["shininess"] = shininess
        if shadows is not None:
            changes["shadows"] = shadows
        if occlusion is not None:
            changes["occlusion"] = occlusion
        if shadow_depth is not None:
            changes["shadow_depth"] = shadow_depth
        return self.replace_layer(id, **changes)

    def swapped_layer(self, id: str, layer: dict[str, Any]) -> Document:
        """A copy where layer ``id`` (at any depth) is ``layer`` — a whole layer of any kind with the same id (an
        import making a multiplier and its normal map one surface layer again)."""
        if layer.get("id") != id:
            raise DocumentError(f"the new layer's id is {layer.get('id')!r}; expected {id!r}", "layers")
        return self._edit_siblings(id, lambda layers, i: layers.__setitem__(i, dict(layer)))

    def without_layer(self, id: str) -> Document:
        """A copy without layer ``id`` (at any depth, a group with its layers; a learned layer conditioned on
        it makes this an error)."""
        return self._edit_siblings(id, lambda layers, i: layers.__delitem__(i))

    def moved_layer(self, id: str, index: int) -> Document:
        """A copy where layer ``id`` is at position ``index`` (0 = bottom) of the list it is in (the top-level
        list, or its group's)."""

        def move(layers: list[dict[str, Any]], i: int) -> None:
            if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(layers):
                raise DocumentError(f"expected a position in [0, {len(layers) - 1}], got {index!r}", f"layer {id!r}")
            layers.insert(index, layers.pop(i))

        return self._edit_siblings(id, move)

    def grouped(self, ids: list[str], group: dict[str, Any]) -> Document:
        """A copy where the layers ``ids`` (siblings: of one list) are the layers of the new group ``group`` (a
        group layer's fields without ``layers``), in their order, at the place of the topmost of them."""
        ids = list(ids)
        if not ids or len(set(ids)) != len(ids):
            raise DocumentError(f"expected one or more distinct layer ids to group, got {ids!r}", "group")

        def wrap(layers: list[dict[str, Any]], i: int) -> None:
            at = [j for j, d in enumerate(layers) if d["id"] in ids]
            if len(at) != len(ids):
                raise DocumentError(
                    f"layers {', '.join(map(repr, ids))} are not all in one list; expected siblings (the "
                    "top-level list, or one group's)",
                    "group",
                )
            children = [layers[j] for j in at]
            for j in reversed(at):
                del layers[j]
            layers.insert(at[-1] - len(at) + 1, {**group, "kind": "group", "layers": children})

        return self._edit_siblings(ids[0], wrap)

    def ungrouped(self, id: str) -> Document:
        """A copy where group ``id`` is replaced by its layers, in place, each moved by the group's offset. A
        group whose own fields change how its layers compose (a mask, opacity below 1, hidden, isolated) is
        refused: ungrouping it would change the composite."""
        layer = self.layer(id)
        if not isinstance(layer, GroupLayer):
            raise DocumentError(f"is a {layer.kind} layer; expected a group to ungroup", f"layer {id!r}")
        if layer.mask is not None or layer.opacity != 1.0 or not layer.visible or layer.isolated:
            raise DocumentError(
                "has a mask, opacity below 1, is hidden or isolated: ungrouping would change the composite; "
                "expected a plain group (visible, opacity 1, pass-through, no mask)",
                f"layer {id!r}",
            )
        dx, dy = layer.offset.x, layer.offset.y

        def spill(layers: list[dict[str, Any]], i: int) -> None:
            children = [
                {**c, "offset": {"x": c["offset"]["x"] + dx, "y": c["offset"]["y"] + dy}} for c in layers[i]["layers"]
            ]
            layers[i : i + 1] = children

        return self._edit_siblings(id, spill)

    def _edit_siblings(self, id: str, edit) -> Document:
        """A validated copy where ``edit(layers, i)`` changed the list (dumped dicts) holding layer ``id`` at ``i``."""
        data = self.model_dump()

        def visit(layers) -> list[dict[str, Any]] | None:
            layers = list(layers)
            for i, d in enumerate(layers):
                if d["id"] == id:
                    edit(layers, i)
                    return layers
                if d["kind"] == "group" and (inner := visit(d["layers"])) is not None:
                    layers[i] = {**d, "layers": inner}
                    return layers
            return None

        layers = visit(data["layers"])
        if layers is None:
            raise DocumentError(f"no layer with id {id!r}; expected one of {', '.join(self.all_ids)}", "layers")
        return self._validated({**data, "layers": layers})

    @classmethod
    def _validated(cls, data: dict[str, Any], where: str | None = None) -> Document:
        try:
            return cls.model_validate(data)
        except ValidationError as err:
            raise document_error(err, where, cls) from None

    # ---- JSON ------------------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """The document as plain JSON data: every field, canonical blend names."""
        return self.model_dump(mode="json")

    def to_json(self) -> str:
        """The stack.json text: full, stable, 2-space indent, trailing newline (see the module doc); a text
        ``validate`` would refuse (too large, too deep) is a ``DocumentError`` instead (``check_serialised``)."""
        text = dumps(self.to_dict()) + "\n"
        check_serialised(text, "stack.json")
        return text

    @classmethod
    def from_dict(cls, data: Any, where: str | None = None) -> Document:
        """Validate parsed JSON data; errors become one-line ``DocumentError``s naming the JSON path."""
        return cls._validated(data, where)

    @classmethod
    def from_json(cls, text: str, where: str = "stack.json") -> Document:
        """Parse and validate stack.json text; ``where`` names the file in error messages."""
        return cls.from_dict(parse_json(text, where), where)


def _is_scalar(value: Any) -> bool:
    return not isinstance(value, (list, dict))


def _inline(value: Any) -> str | None:
    """One-line form of a list of scalars, or of a small object of scalars and such lists."""
    if isinstance(value, list) and all(_is_scalar(v) for v in value):
        return "[" + ", ".join(json.dumps(v, ensure_ascii=False, allow_nan=False) for v in value) + "]"
    if isinstance(value, dict) and all(_is_scalar(v) or _inline(v) is not None for v in value.values()):
        parts = [f"{json.dumps(k, ensure_ascii=False)}: {dumps(v)}" for k, v in value.items()]
        line = "{" + ", ".join(parts) + "}"
        return line if len(line) <= 72 else None
    return None


def dumps(value: Any, indent: int = 0) -> str:
    """JSON, 2-space indent, with small objects and arrays of numbers (colours, ranges) on one line."""
    if _is_scalar(value):
        return json.dumps(value, ensure_ascii=False, allow_nan=False)
    if (line := _inline(value)) is not None:
        return line
    pad, inner = "  " * indent, "  " * (indent + 1)
    if isinstance(value, dict):
        items = [f"{inner}{json.dumps(k, ensure_ascii=False)}: {dumps(v, indent + 1)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + f"\n{pad}}}"
    return "[\n" + ",\n".join(f"{inner}{dumps(v, indent + 1)}" for v in value) + f"\n{pad}]"
