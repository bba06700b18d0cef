"""One learned layer's recipe: everything that decides its pixels, resolved and checked once.

A ``Recipe`` is frozen. It is built in one of two ways, each entering the catalogue once
(``lasagna.catalogue.resolve``):

* ``Recipe.for_edit(stack, request)`` — a new layer from what a user asked (``EditRequest``: the options
  of ``lasagna edit``, of ``lasagna.edit``/``edit_many`` and of the editor's add, in one type);
* ``Recipe.from_layer(stack, layer)`` — a stored learned layer made again (``lasagna render``, the editor's
  jobs) from its ``settings``; a layer whose settings record no ``method`` was never made and is made as
  ``for_edit`` would make it with the preset's defaults (its working size included).

``lasagna.learned.make_layer(recipe, base, id)`` then only computes. Each rule of how a layer is made is
stated here once: the method (``choose_method``), the per-image steps (``default_steps``), the loss of a
prior of one's own, the distillation settings, the working size, the prior and corrective and the SHA-256
of every file they are read from.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from torch import Tensor

from lasagna import catalogue as cat
from lasagna.components import (
    PriorSource,
    changed_weights,
    config_doc,
    file_sha256,
    files_sha256,
    listing_sha256,
)
from lasagna.distill import DistillSettings
from lasagna.document import LearnedLayer
from lasagna.document.preset import (
    METHODS,
    ControlNetRef,
    DiffusersOptions,
    Method,
    Preset,
    SurfaceDefaults,
)
from lasagna.errors import DocumentError, ImageError, LasagnaError, PathError, describe_validation_error
from lasagna.io.image import DEFAULT_EDIT_MAX_PIXELS
from lasagna.io.stack import Stack, resolve_inside
from lasagna.limits import MAX_DISTILL_STEPS
from lasagna.request import METHOD_ALIASES, EditRequest, canonical_method, check_request, layer_kind

# ---- how a layer is made, as its stack records it ------------------------------------------------


class LayerSettings(BaseModel):
    """A learned layer's ``settings`` in its stack (``LearnedLayer.settings`` holds them as JSON): how the
    layer was made, enough to make it again (``lasagna render``).

    ``method`` and ``optimize`` (the per-image steps: after the amortised pass, or of the free layer) are
    always written, ``working_size`` when the layer was made at a working size (`lasagna.compose.resample`);
    ``prior``, its weights' ``prior_sha256``, ``corrective`` and ``distill`` (the resolved
    ``DistillSettings``) only when per-image steps ran. A document may leave any of them out: ``render``
    then makes the layer as ``edit`` would and fills them in.
    """

    model_config = ConfigDict(extra="forbid")

    method: Method | None = Field(None, description="amortised (the preset's generator) or per-image.")
    optimize: int | None = Field(None, ge=0, le=MAX_DISTILL_STEPS, strict=True, description="Per-image steps.")
    prior: str | None = Field(None, description="The prior scored against, by catalogue name or path.")
    prior_sha256: str | None = Field(
        None,
        description="SHA-256 of the prior's model.safetensors (a diffusers prior: of its files' names and SHA-256s, "
        "ControlNets included, as ``weights`` lists them).",
    )
    corrective: str | None = Field(None, description="The LMC-SDS corrective, when the loss used one.")
    controlnets: list[ControlNetRef] | None = Field(None, description="A diffusers prior's ControlNets, as used.")
    diffusers: DiffusersOptions | None = Field(None, description="How a diffusers prior was loaded and run.")
    control_image: str | None = Field(
        None, description="The conditioning image used instead of the base: a PNG inside the stack folder."
    )
    weights: dict[str, str] | None = Field(
        None,
        description="SHA-256 of every file the prior, its ControlNets and the corrective were read from, by name "
        "(prior/…, controlnet<i>/…, corrective/…); `lasagna render` warns when one changed.",
    )
    distill: DistillSettings | None = Field(None, description="The per-image run's resolved settings.")
    working_size: int | None = Field(
        None, ge=8, le=4096, strict=True, description="The long side the layer was made at (absent: the base's size)."
    )

    @field_validator("method", mode="before")
    @classmethod
    def _alias(cls, value: object) -> object:
        return METHOD_ALIASES.get(value, value) if isinstance(value, str) else value

    @classmethod
    def parse(cls, data: Any, where: str) -> LayerSettings:
        """Validate stored settings; a bad field is a one-line ``DocumentError`` at ``where: settings.<field>``."""
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise describe_validation_error(exc, where, cls, DocumentError, prefix="settings") from None

    def to_json(self) -> dict[str, Any]:
        """The JSON the stack stores: the fields in their order, the per-image ones only with ``distill``."""
        data = self.model_dump(mode="json")
        if self.distill is None:
            data = {k: data[k] for k in ("method", "optimize", "working_size")}
        for key in ("controlnets", "diffusers", "control_image", "weights"):  # absent: as before they existed
            if data.get(key) is None:
                data.pop(key, None)
        if self.working_size is None:
            del data["working_size"]  # a layer made at the base's size: the document as before working sizes
        return data


def choose_method(resolved: cat.Resolved, method: str | None) -> Method:
    """``method`` (``free`` is ``per-image``) when given; else the preset's ``method``; else ``amortised`` when
    the preset has a generator. A preset asking for ``amortised`` without a generator falls back to per-image."""
    if method is not None:
        return canonical_method(method)
    if resolved.preset.method == "per-image" or resolved.generator is None:
        return "per-image"
    return "amortised"


def default_steps(resolved: cat.Resolved, method: Method) -> int:
    """Per-image steps when none are given: the preset's ``refine_steps`` after an amortised pass, its
    ``distill.steps`` for a per-image layer."""
    preset = resolved.preset
    return preset.refine_steps if method == "amortised" else preset.distill.steps


# ---- the recipe ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Recipe:
    """How one learned layer is made (module docstring). ``kind``: which kind of learned layer.

    ``method`` and ``steps`` (per-image steps); ``working_size`` (the long side it is made at, None: the
    base's size); ``generator`` (the amortised generator's folder, with ``generator_sha256``; ``stored``: the
    stack's record of the copy it came from, kept by a re-render); ``distill`` (the per-image run's settings,
    None when no per-image step runs) scored by the prior at ``prior`` (``prior_ref`` as recorded,
    ``prior_sha256``) and the corrective at ``corrective``; ``options`` (a diffusers prior's);
    ``weights``: SHA-256 of every file they are read from; ``control``: the ControlNet's image (3, H, W), as
    stored (16-bit codes), or None."""

    preset: Preset
    label: str
    method: Method
    steps: int
    working_size: int | None
    kind: Literal["learned", "surface"] = "learned"
    prompt: str | None = None
    negative_prompt: str | None = None
    generator: Path | None = None
    generator_sha256: str | None = None
    stored: Mapping[str, str] | None = None
    distill: DistillSettings | None = None
    prior: PriorSource | None = None
    prior_ref: str | None = None
    prior_sha256: str | None = None
    corrective: Path | None = None
    corrective_ref: str | None = None
    options: DiffusersOptions | None = None
    weights: Mapping[str, str] = field(default_factory=dict)
    control: Tensor | None = None
    estimator: Path | None = None
    estimator_sha256: str | None = None
    surface: SurfaceDefaults | None = None
    source_light: str | None = None
    source_within: float | None = None  # the given source light's uncertainty (degrees): fused with the fit's
    fit_estimator: Path | None = None  # the untold estimator whose fit it is fused with (``source_within``)

    @classmethod
    def for_edit(
        cls,
        stack: Stack,
        request: EditRequest,
        *,
        catalogue_dirs=None,
        max_pixels: int = DEFAULT_EDIT_MAX_PIXELS,
        resolve: Callable[[Stack], cat.Resolved] | None = None,
    ) -> Recipe:
        """A new layer of ``request`` on ``stack`` (``resolve``: a batch's cached lookup of the preset)."""
        own = _own_prior(request)
        if resolve is not None:
            resolved = resolve(stack)
        else:
            refs = {"prior": own[0], "corrective": own[2], "controlnets": own[1]} if own else {}
            resolved = cat.resolve(request.preset, stack.folder, catalogue_dirs, need_prior=False, **refs)
        p = resolved.preset
        label = check_request(request, p)
        if layer_kind(request, p) == "surface":
            return _surface_recipe(resolved, request, label)
        method = choose_method(resolved, "per-image" if request.own_scored else request.generator)
        steps = request.asked_steps
        if method == "per-image" and steps == 0:
            raise LasagnaError(
                "per-image optimisation with 0 steps would leave the identity edit; expected --optimize N > 0",
                "optimize",
            )
        steps = default_steps(resolved, method) if steps is None else steps
        distill = None
        if steps > 0 or method == "per-image":
            distill = DistillSettings.from_preset(
                p, loss=_edit_loss(request, p), steps=steps, **request.distill_overrides()
            )
            distill = refining(distill) if method == "amortised" else distill
        control = None
        if request.control_image is not None:
            control = read_control_image(request.control_image, (stack.height, stack.width), max_pixels)
        return _made(
            resolved,
            label,
            method,
            steps,
            p.working_size,
            distill,
            user=own is not None,
            prompt=request.prompt,
            negative_prompt=request.negative_prompt,
            options=diffusers_options(p, request.diffusers),
            control=None if control is None else _as_stored_control(control),
            catalogue_dirs=catalogue_dirs,
        )

    @classmethod
    def from_layer(
        cls,
        stack: Stack,
        layer: LearnedLayer,
        *,
        catalogue_dirs=None,
        refine: int | None = None,
        catalogue_generator: bool = False,
    ) -> Recipe:
        """``layer`` of ``stack`` made again from its record. ``refine``: the editor's refine, the recorded run
        again for that many per-image steps (after the amortised pass when the layer records one, else as a
        free layer); ``catalogue_generator``: the catalogue's generator instead of the stack's copy (one not
        saved yet)."""
        where = f"layer {layer.id!r}"
        s = LayerSettings.parse(layer.settings, where)
        refs = {k: _confined_ref(stack, getattr(s, k), f"{where}.settings.{k}") for k in ("prior", "corrective")}
        resolved = cat.resolve(
            layer.preset,
            stack.folder,
            catalogue_dirs,
            need_prior=False,
            **{k: v for k, v in refs.items() if v is not None},
        )
        p = resolved.preset
        if layer.condition.prompt is None:
            p.prompt_for(layer.condition.label)
        chosen = s.method or ("per-image" if refine is not None else choose_method(resolved, None))
        n = refine if refine is not None else s.optimize
        n = default_steps(resolved, chosen) if n is None else n
        distill = None
        if n > 0 or chosen == "per-image":
            if s.distill is not None:
                distill = s.distill if refine is None else s.distill.model_copy(update={"steps": refine})
            else:
                distill = DistillSettings.from_preset(p, steps=n)
                distill = refining(distill) if chosen == "amortised" else distill
        # Settings that record a method were made: without a working size, at the base's size (a layer made
        # before working sizes). Settings without one were never made: made as an edit makes them.
        side = s.working_size if s.working_size is not None else (None if s.method is not None else p.working_size)
        recipe = _made(
            resolved,
            layer.condition.label,
            chosen,
            n,
            side,
            distill,
            user=False,
            prompt=layer.condition.prompt,
            negative_prompt=layer.condition.negative_prompt,
            options=s.diffusers or p.diffusers or DiffusersOptions(),
            control=_stored_control(stack, s.control_image, where),
            stored=None if catalogue_generator else _stored_generator(stack, layer, chosen, where),
            catalogue_dirs=catalogue_dirs,
        )
        _warn_changed(recipe, s, where)
        return recipe

    def pending_settings(self) -> dict[str, Any]:
        """The settings of a layer added to be made later (the editor's per-image add): how to make it."""
        return LayerSettings(method=self.method, optimize=self.steps, working_size=self.working_size).to_json()


def _made(
    resolved: cat.Resolved,
    label: str,
    method: Method,
    steps: int,
    side: int | None,
    distill: DistillSettings | None,
    *,
    user: bool,
    prompt: str | None,
    negative_prompt: str | None,
    options: DiffusersOptions,
    control: Tensor | None,
    stored: tuple[Path, dict[str, str]] | None = None,
    catalogue_dirs=None,
) -> Recipe:
    """The recipe of these choices, its generator and (with ``distill``) its prior and corrective checked;
    ``catalogue_dirs`` where a recorded surface start's estimator is looked for."""
    p = resolved.preset
    generator, generator_sha, record = None, None, None
    if method == "amortised":
        if stored is not None:
            generator, record = stored
            generator_sha = record.get("sha256")
        else:
            generator = amortised_generator(resolved)
            generator_sha = file_sha256(generator / "model.safetensors")
    scoring: dict[str, Any] = {}
    if distill is not None:
        scoring = _scoring(resolved, distill.loss, options, user=user)
    start: dict[str, Any] = {}
    if distill is not None and distill.start == "surface" and method == "per-image":
        # A free layer that starts from a surface estimate (lasagna.learned._surface_start): made as its settings
        # record (``start_surface``), else as the preset says (settings recorded before the start was recorded).
        surface = distill.start_surface or p.surface
        if surface is None or (resolved.estimator is None and surface is p.surface):
            raise resolved.missing.get("estimator") or LasagnaError(
                f"the free layer starts from a surface, and preset {p.name!r} names no surface estimator; expected "
                "a preset with `surface`",
                "distill.start",
            )
        estimator = resolved.estimator
        if p.surface is None or surface.estimator != p.surface.estimator or estimator is None:
            # The layer was made with another estimator than the preset names now: that one, found by its name.
            relative = resolved.preset_file.parent if "/" in surface.estimator else None
            estimator = cat.find(surface.estimator, "estimator", catalogue_dirs=catalogue_dirs, relative_to=relative)
        start = dict(
            estimator=estimator,
            estimator_sha256=file_sha256(estimator / "model.safetensors"),
            surface=surface,
        )
    return Recipe(
        preset=p,
        label=label,
        method=method,
        steps=steps,
        working_size=side,
        prompt=prompt,
        negative_prompt=negative_prompt,
        generator=generator,
        generator_sha256=generator_sha,
        stored=record,
        distill=distill,
        control=control,
        **scoring,
        **start,
    )


def _surface_recipe(resolved: cat.Resolved, request: EditRequest, label: str) -> Recipe:
    """The recipe of a surface layer (``kind="surface"``) lit by ``label`` (checked: ``check_request``): the
    preset's estimator at its working size, then ``refine_steps`` multi-light score-distillation steps
    (``lasagna.distill.surface``) scored by its prior; told the source light (``request.source_light``), the
    estimator, wall gates and refinement size of ``surface.told`` when the preset names one. The condition is any
    light, named or ``az=…,el=…``: a surface is lit by every light alike."""
    p = resolved.preset
    surface, estimator = p.surface, resolved.estimator
    if request.source_light is not None and p.surface.told is not None:
        # Told its source light, the layer reads the estimator the preset names for a told light (SurfaceDefaults.told).
        told = p.surface.told
        update = {"estimator": told.estimator, "wall_relief": told.wall_relief, "closer_walls": told.closer_walls}
        if told.refine_size is not None:
            update["refine_size"] = told.refine_size
        surface = p.surface.model_copy(update=update)
        estimator = resolved.told_estimator
        if estimator is None:
            raise resolved.missing["told_estimator"]
    if estimator is None:
        raise resolved.missing.get("estimator") or LasagnaError(f"preset {p.name!r} names no estimator", "surface")
    reads = (config_doc(estimator).get("config") or {}).get("input")
    if request.source_light is not None and reads != "lit":
        # An estimator of the unlit base has no source light to be told (a shading layer is S(light) alone).
        raise LasagnaError(
            f"preset {p.name!r} reads an unlit image ({p.surface.estimator!r}), so there is no source light to give; "
            "expected --from only with a relight (a lit image), e.g. --layer relight",
            "from",
        )
    steps = request.asked_steps
    steps = p.surface.refine_steps if steps is None else steps
    distill = None
    scoring: dict[str, Any] = {}
    if steps > 0:
        distill = DistillSettings.from_preset(p, loss=request.loss or "sds", steps=steps, **request.distill_overrides())
        scoring = _scoring(resolved, distill.loss, diffusers_options(p, None), user=False)
    return Recipe(
        preset=p,
        label=label,
        method="per-image" if steps > 0 else "amortised",
        steps=steps,
        working_size=p.surface.working_size,
        kind="surface",
        estimator=estimator,
        estimator_sha256=file_sha256(estimator / "model.safetensors"),
        surface=surface,
        source_light=request.source_light,
        source_within=request.source_within,
        fit_estimator=resolved.estimator if request.source_within is not None else None,
        distill=distill,
        **scoring,
    )


def amortised_generator(resolved: cat.Resolved) -> Path:
    """The preset's amortised generator's folder; a one-line refusal when it has none."""
    if resolved.generator is None:
        name = resolved.preset.name
        raise LasagnaError(
            f"preset {name!r} has no amortised generator yet (train one: lasagna train-layer --preset {name}); "
            "expected --generator free",
            "generator",
        )
    return resolved.generator


def _need(resolved: cat.Resolved, kind: Literal["prior", "corrective"]) -> Path:
    """The folder of ``kind``; its one-line error (from the lookup) when it was named but not found."""
    folder = resolved.prior if kind == "prior" else resolved.corrective
    if folder is None:
        raise resolved.missing.get(kind) or LasagnaError(f"preset {resolved.preset.name!r} names no {kind}", kind)
    return folder


def _scoring(resolved: cat.Resolved, loss: str, options: DiffusersOptions, *, user: bool) -> dict[str, Any]:
    """The prior and corrective a per-image run is scored with, as ``Recipe`` fields, every file's SHA-256."""
    if loss == "lmc-sds" and resolved.corrective_ref is None:  # before the prior: a refusal costs nothing
        hint = (
            "--corrective PATH (fit one: lasagna train-corrective --kind spectral --prior PATH)"
            if user
            else "another --loss or a preset with a corrective"
        )
        raise LasagnaError(
            f"loss 'lmc-sds' needs a corrective (b-hat of LMC-SDS eq. 10) and none is given; expected {hint}",
            "loss",
        )
    _need(resolved, "prior")  # raises, listing the priors there are
    source = resolved.source
    diffusers = source.kind == "diffusers"
    weights = files_sha256(source.files(options.variant if diffusers else None))
    corrective = None
    if loss == "lmc-sds":
        corrective = _need(resolved, "corrective")
        weights.update(files_sha256({f"corrective/{n}": corrective / n for n in ("model.safetensors", "config.json")}))
    return {
        "prior": source,
        "prior_ref": resolved.prior_ref,
        "prior_sha256": listing_sha256(weights) if diffusers else weights.get("prior/model.safetensors"),
        "corrective": corrective,
        "corrective_ref": resolved.corrective_ref if loss == "lmc-sds" else None,
        "options": options if diffusers else None,
        "weights": weights,
    }


# ---- the rules ---------------------------------------------------------------------------------------------


def refining(settings: DistillSettings) -> DistillSettings:
    """Settings for per-image steps after the amortised pass: they start from an edit, not the identity, so
    the L2 pull toward the input that eases a run out of the identity is off (score only), and no lock holds
    them to a surface start they do not have (``distill.lock``, ``distill.objects_only``)."""
    from lasagna.distill.schedules import Weights

    return settings.model_copy(update={"weights": Weights(), "lock": "none", "objects_only": False})


def _edit_loss(request: EditRequest, preset: Preset) -> str | None:
    """The loss asked for; with one's own prior and none asked, LMC-SDS when a corrective is given, else SDS
    in place of the preset's LMC-SDS (the preset's corrective belongs to its own prior)."""
    if request.loss is not None or request.prior is None:
        return request.loss
    default = preset.distill.loss
    return "lmc-sds" if request.corrective is not None else ("sds" if default == "lmc-sds" else None)


def diffusers_options(preset: Preset, diffusers: DiffusersOptions | dict | None) -> DiffusersOptions:
    """The diffusers options of an edit: ``DiffusersOptions`` as given, or a dict of fields over the preset's."""
    if isinstance(diffusers, DiffusersOptions):
        return diffusers
    base = preset.diffusers or DiffusersOptions()
    try:
        return DiffusersOptions.model_validate({**base.model_dump(), **(diffusers or {})})
    except ValidationError as err:
        raise describe_validation_error(err, "diffusers", DiffusersOptions) from None


def _own_prior(request: EditRequest) -> tuple[str, tuple[ControlNetRef, ...], str | None] | None:
    """The request's prior of one's own as (prior, ControlNets, corrective): a folder that exists by its
    absolute path, anything else a catalogue name; None when none is given."""
    if request.prior is None:
        return None
    nets = []
    for net in request.controlnets:
        path, scale = net if isinstance(net, tuple) else (net, None)
        if not Path(path).is_dir():
            raise PathError("does not exist; expected a ControlNet folder written by save_pretrained", str(path))
        nets.append(ControlNetRef(path=str(Path(path).resolve()), scale=scale))

    def absolute(ref):
        if ref is None:
            return None
        return str(Path(ref).resolve()) if Path(ref).is_dir() or isinstance(ref, os.PathLike) else str(ref)

    return absolute(request.prior), tuple(nets), absolute(request.corrective)


def read_control_image(source, size: tuple[int, int], max_pixels: int = DEFAULT_EDIT_MAX_PIXELS) -> Tensor:
    """A conditioning image (a file, tensor (C, H, W), array or PIL image) as (3, H, W) in [0, 1] at the base's
    ``size``: another size of the same aspect (within 1 %) is resampled; another aspect is refused."""
    from lasagna.distill.objective import resize

    if isinstance(source, (str, os.PathLike)):
        from lasagna.io.image import read_image_file

        img = torch.from_numpy(read_image_file(source, max_pixels=max_pixels).color).float()
        where = str(source)
    else:
        img = Stack.from_image(source).tensors["base"].float()
        where = "control_image"
    if img.shape[0] == 1:
        img = img.expand(3, -1, -1)
    h, w = img.shape[-2:]
    if abs(h * size[1] - w * size[0]) > 0.01 * h * size[1]:
        raise ImageError(
            f"is {w}x{h}; expected the aspect of the image it conditions, {size[1]}x{size[0]} (any size)", where
        )
    return resize(img[:3][None], size)[0].clamp(0, 1)


def _as_stored_control(control: Tensor) -> Tensor:
    """The control image as its 16-bit PNG in the stack holds it, so a re-render sees the same values."""
    return control.float().clamp(0, 1).mul(65535).round().div(65535)


def _stored_control(stack: Stack, ref: str | None, where: str) -> Tensor | None:
    """A layer's stored conditioning image (``settings.control_image``), or None."""
    if ref is None:
        return None
    from lasagna.io.image import read_image_file

    path = resolve_inside(stack.folder, ref, f"{where}.settings.control_image") if stack.folder else None
    if path is None or not path.is_file():
        raise PathError(
            f"{ref!r} does not exist; expected the layer's conditioning image in the stack folder",
            f"{where}.settings.control_image",
        )
    return torch.from_numpy(read_image_file(path, max_pixels=stack.width * stack.height).color).float()


def _confined_ref(stack: Stack, ref: str | None, where: str) -> str | None:
    """A stored prior/corrective reference as ``render`` may follow it: a catalogue name, or a relative
    path inside the stack folder. Anything else is refused before the filesystem is asked about it, so
    the message says nothing about what exists outside the folder."""
    if ref is None or ("/" not in ref and "\\" not in ref):
        return ref
    parts = ref.replace("\\", "/").split("/")
    if ref.startswith(("/", "\\")) or ":" in parts[0] or ".." in parts or stack.folder is None:
        raise PathError(
            f"{ref!r} is not a catalogue name or a relative path inside the stack folder; expected one of those",
            where,
        )
    try:
        return str(resolve_inside(stack.folder, ref, where))
    except PathError:
        raise PathError(f"{ref!r} leaves the stack folder (through a link); expected a path inside it", where) from None


def _stored_generator(
    stack: Stack, layer: LearnedLayer, method: Method, where: str
) -> tuple[Path, dict[str, str]] | None:
    """The stack's copy of the generator ``layer`` was made with (its folder and record), checked against the
    recorded SHA-256s; None when the layer records none (the catalogue's then runs) or is not amortised."""
    ref = layer.generator
    if method != "amortised" or ref is None:
        return None
    if stack.folder is None:
        raise PathError(
            "the stack has no folder to find its generator in; expected a stack loaded from a folder", where
        )
    ckpt = resolve_inside(stack.folder, ref.checkpoint, f"{where}.generator.checkpoint")
    if not ckpt.is_file():
        raise PathError(
            f"{ref.checkpoint!r} does not exist; expected the generator's weights", f"{where}.generator.checkpoint"
        )
    if ref.sha256 is not None and file_sha256(ckpt) != ref.sha256:
        raise LasagnaError(
            "the generator's weights do not match the recorded sha256; expected the file the layer was made with",
            f"{where}.generator.checkpoint",
        )
    config = ckpt.parent / "config.json"
    if ref.config_sha256 is not None:
        if not config.is_file() or file_sha256(config) != ref.config_sha256:
            raise LasagnaError(
                "the generator's config.json does not match the recorded config_sha256; expected the config "
                "the layer was made with",
                f"{where}.generator.config_sha256",
            )
    elif ref.sha256 is not None:
        warnings.warn(
            f"{where}: the generator's config.json is under no checksum (a stack written before config_sha256); "
            "its vocabulary is trusted as found",
            stacklevel=4,
        )
    return ckpt.parent, ref.model_dump(mode="json")


def _warn_changed(recipe: Recipe, s: LayerSettings, where: str) -> None:
    """One warning when a file the layer was made with changed since (it is made with the current one)."""
    changed = changed_weights(s.weights, dict(recipe.weights)) if s.weights is not None else []
    if changed:
        more = f" (+{len(changed) - 1} more)" if len(changed) > 1 else ""
        warnings.warn(
            f"{where}: {changed[0]}{more} differs from the file the layer was made with (sha256); the layer is "
            "re-rendered with the current weights",
            stacklevel=3,
        )
    elif s.weights is None and s.prior_sha256 is not None and recipe.prior_sha256 not in (None, s.prior_sha256):
        warnings.warn(
            f"{where}: the catalogue's prior {recipe.prior_ref!r} differs from the one the layer was "
            "made with (sha256); the layer is re-rendered with the current one",
            stacklevel=3,
        )


__all__ = [
    "METHODS",
    "LayerSettings",
    "Recipe",
    "amortised_generator",
    "choose_method",
    "default_steps",
    "refining",
    "diffusers_options",
    "read_control_image",
]
