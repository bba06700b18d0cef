"""What a user asks of a new learned layer, and every check of it that needs no more than the preset: torch-free.

``EditRequest`` is the one request type of ``lasagna.edit``, ``edit_many``, ``lasagna edit`` and the editor's add;
``check_request(request, preset)`` states, once, what a request may ask of a preset — the layer kind
(``layer_kind``), a surface layer's light, a free layer's label in the preset's vocabulary, and the options each
kind refuses. ``lasagna.recipe.Recipe.for_edit`` calls it before it resolves the preset's parts; ``lasagna edit``
calls it before torch is loaded, so a typing mistake is refused in a fraction of a second (torch's import alone
is 1.5–2 s on the project's CPUs).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from lasagna.document.condition import parse_direction
from lasagna.document.preset import METHODS, PRESET_LAYER_KINDS, DiffusersOptions, Method, Preset
from lasagna.errors import ConditionError, LasagnaError

MAX_WITHIN = 90.0
"""The largest uncertainty (degrees) a given source light may carry (``EditRequest.source_within``): beyond it a
reading says nothing the estimator's fit does not."""

PROMPT_LABEL = "prompt"  # the label of a layer asked for by free text alone (it names the prompt, no more)

# How a learned layer is made (``lasagna.editing`` describes both; the names are the document tier's,
# ``lasagna.document.preset.Method``). ``free`` — the CLI's ``--generator free``, "a free per-pixel
# layer" — names the per-image method and is accepted wherever a method is read.
METHOD_ALIASES: dict[str, str] = {"free": "per-image"}


def canonical_method(name: object, where: str = "generator") -> Method:
    """The method ``name`` names (``free`` is ``per-image``); a ``LasagnaError`` listing them otherwise."""
    name = METHOD_ALIASES.get(name, name) if isinstance(name, str) else name
    if name not in METHODS:
        raise LasagnaError(f"method is {name!r}; expected one of {', '.join(METHODS)} (or 'free' for per-image)", where)
    return name  # type: ignore[return-value]


def check_steps(optimize: Any, steps: Any = None) -> int | None:
    """The per-image steps asked for by ``optimize`` or its second name ``steps`` (the same number, or one of
    them), a non-negative integer; None: the default. The one statement of their agreement."""
    if optimize is not None and steps is not None and optimize != steps:
        raise LasagnaError(
            f"optimize {optimize} and steps {steps} differ; expected one of them (they are the same number)", "steps"
        )
    n = optimize if optimize is not None else steps
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 0):
        raise LasagnaError(f"expected a non-negative integer, got {n!r}", "optimize")
    return n


def check_preset_name(preset: Any) -> str:
    """``preset`` if it is a catalogue name; a one-line refusal of a ``Preset`` object or a path."""
    if preset is not None and not isinstance(preset, (str, os.PathLike)):
        # A Preset object has no folder: the layer's record could not name it for a later render.
        raise LasagnaError(
            f"got a {type(preset).__name__}; expected a catalogue name (write the preset with preset.to_json() "
            "into <folder>/<name>/preset.json and add <folder> with catalogue_dirs= or LASAGNA_LAYERS)",
            "preset",
        )
    if preset is None or "/" in str(preset) or isinstance(preset, os.PathLike):
        raise LasagnaError(
            f"preset {str(preset)!r} is not a name; expected a catalogue name (add a catalogue folder "
            "with LASAGNA_LAYERS)",
            "preset",
        )
    return preset


@dataclass(frozen=True)
class EditRequest:
    """The options a user gives for a new learned layer, as given (``Recipe.for_edit`` resolves them): the one
    request type of ``lasagna.edit``, ``edit_many``, ``lasagna edit`` and the editor's add.

    ``generator``: the method (``amortised``, ``per-image`` or its alias ``free``; default the preset's);
    ``optimize``: per-image steps (``steps`` is its second name); ``loss``, ``guidance``, ``seed``, ``lr``,
    ``t_min``, ``t_max``, ``aspect``, ``particles``: over the preset's distillation defaults; ``prior``,
    ``controlnets``, ``corrective``, ``control_image``, ``diffusers``: a prior of one's own; ``prompt`` and
    ``negative_prompt``: free text (``lasagna.editing``'s module docstring)."""

    preset: str = "shading"
    condition: str | None = None
    on: str | None = None
    id: str | None = None
    generator: str | None = None
    optimize: int | None = None
    steps: int | None = None
    loss: str | None = None
    guidance: float | None = None
    seed: int | None = None
    lr: float | None = None
    t_min: float | None = None
    t_max: float | None = None
    aspect: str | None = None
    particles: int | None = None
    prior: str | os.PathLike | None = None
    controlnets: Sequence[str | os.PathLike | tuple[str | os.PathLike, float]] = ()
    corrective: str | os.PathLike | None = None
    control_image: Any = None
    prompt: str | None = None
    negative_prompt: str | None = None
    diffusers: DiffusersOptions | dict | None = None
    layer_kind: str | None = None
    source_light: str | None = None
    source_within: float | None = None

    def __post_init__(self) -> None:
        check_preset_name(self.preset)
        check_steps(self.optimize, self.steps)
        if self.generator is not None:
            canonical_method(self.generator)
        for text, name in ((self.prompt, "prompt"), (self.negative_prompt, "negative_prompt")):
            if text is not None and not (isinstance(text, str) and text.strip()):
                raise ConditionError(f"got {text!r}; expected non-empty text", name)
        if self.layer_kind is not None and self.layer_kind not in PRESET_LAYER_KINDS:
            raise LasagnaError(
                f"got {self.layer_kind!r}; expected one of {', '.join(PRESET_LAYER_KINDS)}", "layer_kind"
            )
        if self.source_light is not None:
            try:
                parse_direction(self.source_light)
            except ConditionError as exc:  # what a light is, said of --from
                raise exc.at("from") from None
        if self.source_within is not None:
            if self.source_light is None:
                raise LasagnaError(
                    "--within is how far a given source light may be off; expected --from LIGHT too", "within"
                )
            w = self.source_within
            if isinstance(w, bool) or not isinstance(w, (int, float)) or not 0.0 < float(w) <= MAX_WITHIN:
                raise LasagnaError(f"got {w!r}; expected degrees in (0, {MAX_WITHIN:g}]", "within")
        if self.prior is None and (self.controlnets or self.corrective is not None):
            raise LasagnaError(
                "ControlNets and a corrective go with a prior of one's own; expected --prior PATH too", "prior"
            )

    @property
    def asked_steps(self) -> int | None:
        """The per-image steps asked for (``optimize`` or ``steps``), None for the default."""
        return check_steps(self.optimize, self.steps)

    @property
    def own_scored(self) -> bool:
        """Scored per image by something the amortised generator never saw: free text or one's own prior."""
        return self.prompt is not None or self.prior is not None

    def distill_overrides(self) -> dict[str, Any]:
        """The ``DistillSettings`` fields given (over the preset's defaults), loss aside."""
        names = ("guidance", "seed", "lr", "t_min", "t_max", "aspect", "particles")
        return {k: getattr(self, k) for k in names if getattr(self, k) is not None}


def layer_kind(request: EditRequest, preset: Preset) -> str:
    """The layer kind of a new edit: the one asked for; else free when the request names what only a free layer
    uses (a method — ``--generator`` — a prior of one's own, a prompt); else a surface when it gives a source light
    (``--from``: what only a surface relight reads; docs/BENCHMARKS.md round 19, rule FK); else the preset's
    ``layer_kind``."""
    if request.layer_kind is not None:
        return request.layer_kind
    if request.generator is not None or request.own_scored:
        return "free"
    if request.source_light is not None and preset.surface is not None:
        return "surface"
    return preset.layer_kind


def check_request(request: EditRequest, preset: Preset) -> str:
    """The label of a new layer of ``preset`` as ``request`` asks for it, after every check that needs the preset
    alone (module docstring): a surface layer needs a preset with ``surface``, no method, prior or prompt of its
    own, and a light (named or ``az=…,el=…``) as its condition; a free layer takes no source light, a label of the
    preset's vocabulary unless a prompt is given, and no amortised generator with a prior or prompt of its own."""
    if layer_kind(request, preset) == "surface":
        if preset.surface is None:
            raise LasagnaError(
                f"preset {preset.name!r} names no surface estimator; expected a preset with `surface` (e.g. "
                "shading, relight) or --layer-kind free",
                "layer_kind",
            )
        if request.own_scored or request.generator is not None:
            raise LasagnaError(
                "a surface layer is made by its estimator and the preset's prior; expected no --generator, --prior "
                "or --prompt with --layer-kind surface",
                "layer_kind",
            )
        label = request.condition if request.condition is not None else preset.vocabulary[0]
        parse_direction(label)  # ConditionError saying what a light is
        return label
    if request.source_light is not None:
        raise LasagnaError("a source light is what a surface relight divides by; expected --layer-kind surface", "from")
    label = request.condition
    if label is None:
        label = PROMPT_LABEL if request.prompt is not None else preset.vocabulary[0]
    if request.prompt is None:
        preset.prompt_for(label)  # ConditionError listing the vocabulary
    if request.own_scored and request.generator is not None and canonical_method(request.generator) == "amortised":
        raise LasagnaError(
            "the amortised generator was trained with the preset's prior and labels; expected --generator free "
            "with --prior or --prompt",
            "generator",
        )
    return label


__all__ = [
    "METHOD_ALIASES",
    "PROMPT_LABEL",
    "EditRequest",
    "canonical_method",
    "check_preset_name",
    "check_request",
    "check_steps",
    "layer_kind",
]
