"""Learned-layer presets (``layers/<name>/preset.json``): what a learned layer is and how to distil it.

A preset fixes the layer's blend, channel count and value range (the Lasagna paper's shading layer
is a 1-channel luminosity multiplier, its colour layer an alpha-linear RGBA layer), names the
conditional prior that scores it and, for LMC-SDS (Alldieck et al., eq. 10), the corrective b̂,
lists the condition vocabulary with the prompt template ("A photo of an object with [r] lighting",
Lasagna Sec. 3), and gives default distillation settings. Weights are referenced by name and
resolved by the priors tier; this module only reads JSON. See layers/README.md.
"""

from __future__ import annotations

import os
import string
from pathlib import Path
from typing import Annotated, Any, Literal, get_args

from pydantic import ConfigDict, Field, Strict, ValidationError, field_validator, model_validator

from lasagna.document.condition import NAMED_DIRECTIONS, parse_direction
from lasagna.document.models import dumps
from lasagna.document.types import (
    RANGE_FOR_BLEND_SCHEMA,
    UNIT_RANGE,
    Blend,
    FiniteFloat,
    LayerId,
    NameOrPath,
    Range,
    StrictModel,
    Unit,
    check_range_for_blend,
)
from lasagna.document.validation import RuleError, document_error, parse_json, read_json_text
from lasagna.errors import ConditionError, DocumentError
from lasagna.limits import MAX_DISTILL_STEPS, MAX_PARTICLES

# The score-distillation losses a preset (and ``lasagna edit --loss``) may name: declared here, in the
# tier every other reads; ``lasagna.losses`` registers one implementation under each name.
LossName = Literal["sds", "lmc-sds", "dds", "nfsd", "ms-sds"]
LOSS_NAMES: tuple[str, ...] = get_args(LossName)


# How a learned layer is made: ``amortised`` (the preset's trained generator, one forward pass, then
# ``refine_steps`` per-image steps from it) or ``per-image`` (a free layer optimised for this image,
# ``distill.steps`` steps). Declared here, in the tier every other reads; ``lasagna.learned`` runs them.
Method = Literal["amortised", "per-image"]
METHODS: tuple[str, ...] = get_args(Method)


# How a view of another aspect than the prior's is made (``lasagna.distill.objective``): ``letterbox`` keeps
# the image's aspect (scaled to fit, the rest filled), ``stretch`` resizes it to the prior's shape.
Aspect = Literal["letterbox", "stretch"]
ASPECTS: tuple[str, ...] = get_args(Aspect)

# Where a layer's luminance comes from: its own values (``free``) or the base's Rec. 709 luma (``base``: colour over
# luminance, the colour preset's; ``lasagna.generators.layer.composite`` and ``lasagna.compose.resample``).
Luminance = Literal["free", "base"]

# How a layer made at the working size is enlarged to the image's: ``bilinear``, or ``guided`` — the fast guided filter
# (``lasagna.compose.resample.guided_upsample``) with the base's full-size Rec. 709 luma as guide, so the layer's
# edges follow the image's. (A colour-over-luminance layer has its own guided rule, ``upsample_colour``.)
Enlarge = Literal["bilinear", "guided"]
# How a surface layer's normals are enlarged (``SurfaceDefaults.enlarge``): ``bicubic`` (continuous slopes),
# ``guided`` by the image's luma as above, or ``bilateral`` — joint bilateral upsampling with the luma as guide
# (``lasagna.compose.resample.joint_bilateral_upsample``).
SurfaceEnlarge = Literal["bicubic", "guided", "bilateral"]

# Floating-point types a diffusers prior may run in ("auto": float16 on CUDA, float32 elsewhere).
TorchDtype = Literal["auto", "float32", "float16", "bfloat16"]
TORCH_DTYPES: tuple[str, ...] = get_args(TorchDtype)


FreeStart = Literal["identity", "surface"]
"""Where a per-image free layer starts (``DistillDefaults.start``, recorded in ``DistillSettings.start``)."""

FreeLock = Literal["none", "planar"]
"""What of its surface start a per-image free layer keeps (``DistillDefaults.lock``, recorded in
``DistillSettings.lock``; only with ``start`` 'surface', and not after an amortised pass): nothing, or its planar
trend — the least-squares plane of log(layer / start) is removed after the steps (``lasagna.learned.planar_lock``),
so the distillation may correct the start's level and shape but not tilt it: a relight started from a surface keeps
the surface's direction."""


class DistillDefaults(StrictModel):
    """Default settings of a per-image distillation run (overridable per layer via ``settings``)."""

    loss: LossName = Field("sds", description="Score-distillation loss: sds, lmc-sds, dds, nfsd or ms-sds.")
    guidance: FiniteFloat = Field(
        1.0,
        gt=0,
        description="Classifier-free guidance weight omega in eps_u + omega * (eps_c - eps_u).",
    )
    steps: int = Field(150, ge=1, strict=True, description="Optimisation steps.")
    lr: FiniteFloat = Field(0.03, gt=0, description="Adam learning rate.")
    t_min: Unit = Field(0.02, description="Lower end of t ~ U(t_min, t_max), as a fraction of the schedule.")
    t_max: Unit = Field(0.98, description="Upper end of t ~ U(t_min, t_max).")
    seed: int = Field(0, ge=0, strict=True, description="Random seed of noise and timesteps.")
    particles: int = Field(
        1,
        ge=1,
        le=MAX_PARTICLES,
        strict=True,
        description="Free layers optimised per image, each with its own noise draws, averaged at the end: "
        "an ensemble that averages out the score's noise (costs about as many network passes).",
    )
    particle_mirrors: bool = Field(
        False,
        strict=True,
        description="The particles as a mirror ensemble: particle j scores the image mirrored by the j-th of (none, "
        "left-right, top-bottom, both), its light condition mirrored with it, and its layer is mirrored back before "
        "the mean, so the prior's direction-specific errors average out as its noise does. Light conditions only.",
    )
    whole_fraction: Unit = Field(
        0.4,
        description="For an image larger than the prior: the fraction of the steps on the whole image, "
        "downsampled to the prior's size; the rest on random crops at native resolution (LMC-SDS, Sec. 5). "
        "1 = whole image only, for layers that should stay smooth.",
    )
    aspect: Aspect = Field(
        "letterbox",
        description="An image of another aspect than the prior's: 'letterbox' scales it to fit and fills the rest "
        "(the aspect is kept), 'stretch' resizes it to the prior's shape.",
    )
    start: FreeStart = Field(
        "identity",
        description="Where a per-image free layer starts: 'identity' (the unchanged image), or 'surface' — the "
        "preset's surface estimate rendered under the condition (a relight: S(l)/S(l_src), the source light fitted), "
        "which the distillation then refines per pixel. Needs the preset's `surface`.",
    )
    lock: FreeLock = Field(
        "none",
        description="What of its start a free layer keeps: 'none', or 'planar' — the least-squares plane of "
        "log(layer / start) is removed after the steps, so the distillation corrects the start's level and curved "
        "parts but cannot tilt it (a relight started from a surface keeps the surface's light direction).",
    )
    objects_only: bool = Field(
        False,
        strict=True,
        description="The free layer corrects its surface start on the objects only: log(layer / start) times the "
        "surface estimator's silhouette probability (walls keep the start, so a flat painted wall stays flat). "
        "Needs distill.start 'surface' and an estimator with a silhouette head.",
    )

    @model_validator(mode="after")
    def _t_interval(self) -> DistillDefaults:
        if not self.t_min < self.t_max:
            raise RuleError(f"t_min {self.t_min} >= t_max {self.t_max}; the rule is t_min < t_max", loc=("t_min",))
        return self


class DiffusersOptions(StrictModel):
    """How a diffusers prior is loaded and run (``lasagna.priors.diffusers``); other priors ignore it."""

    torch_dtype: TorchDtype = Field(
        "auto", description="Type the networks are read and run in; auto: float16 on CUDA, float32 elsewhere."
    )
    variant: str | None = Field(
        None, min_length=1, description="Weight files' variant, e.g. 'fp16' (diffusion_pytorch_model.fp16.safetensors)."
    )
    cpu_offload: bool = Field(False, description="Keep each network on the CPU until it runs (needs CUDA).")
    attention_slicing: bool = Field(False, description="Compute attention in slices: less memory, a little slower.")
    channels_last: bool = Field(False, description="NHWC activations in the UNet and ControlNets (faster on GPUs).")
    latent: Literal["mean", "sample"] = Field(
        "mean", description="The VAE posterior's mean, or a seeded sample of it, as the latent."
    )
    conditioning_scale: FiniteFloat = Field(
        1.0, ge=0, description="Scale of every ControlNet's residuals that has no scale of its own."
    )


class ControlNetRef(StrictModel):
    """A ControlNet of a diffusers prior: its folder (written by save_pretrained) and residual scale."""

    path: str = Field(min_length=1, description="The ControlNet's folder (absolute, or relative to the entry).")
    scale: FiniteFloat | None = Field(None, ge=0, description="Residual scale; None: the options' conditioning_scale.")


class PriorLink(StrictModel):
    """A catalogue entry that points at a diffusers prior elsewhere on disk (``<catalogue>/<name>/config.json``,
    written by ``lasagna prior add``): the weights stay where they are, the catalogue names them."""

    format: Literal["lasagna.prior_link"] = Field(description="Always 'lasagna.prior_link'.")
    version: Literal[1] = Field(description="Format version; this is version 1.")
    path: str = Field(min_length=1, description="The diffusers pipeline folder (absolute).")
    controlnets: tuple[ControlNetRef, ...] = Field((), description="Its ControlNets, in order.")


# The world tasks a preset's generator (and a prior) is trained on (``lasagna.training.tasks``): what the base
# layer is and what the true layer is. A preset that says none gets its blend's (``Preset.world_task``).
WorldTask = Literal["relight", "colorize", "light", "relit"]
WORLD_TASKS: tuple[str, ...] = get_args(WorldTask)  # the names, torch-free (the training commands' --task choices)
TASK_FOR_BLEND: dict[str, str] = {"multiply": "relight", "normal": "colorize", "plus": "light"}


LayerKind = Literal["free", "surface"]
"""What a multiply preset's layer is: ``free`` — a per-pixel multiplier (a generator's or a per-image one);
``surface`` — a surface (a height field's normals) rendered under the light (`lasagna.compose.surface`)."""
PRESET_LAYER_KINDS: tuple[str, ...] = ("free", "surface")

ReadSide = Annotated[int, Strict(), Field(ge=8, le=4096)]
"""A long side, in pixels, that a surface is read or refined at (``CloserWalls.size``, ``refine_size``)."""

Symmetry = Literal["none", "mirrors", "dihedral"]
"""A surface estimator's symmetry ensemble (`lasagna.generators.surface`): one pass; the image and its three mirror
images, each estimate mapped back and averaged; those and their transposes (all eight symmetries of the square)."""
SYMMETRIES: tuple[str, ...] = get_args(Symmetry)

SourceElevation = Literal["fit", "walls"]
"""Where a lit estimate's source light's elevation comes from (``SurfaceDefaults.source_elevation``): the fit of the
surface's normals to the estimated source shading, or the estimated source shading's level on the walls."""


class CloserWalls(StrictModel):
    """A second read of the image, closer, for a surface layer's walls: the estimator reads the image at ``size`` as
    well as at the working size, calms that read's walls by ``wall_relief``, and the layer's normals are the
    working-size read on the objects and the closer read on the walls, mixed by the working-size read's silhouette
    probability (`lasagna.learned.walls_read_closer`). Read closer, the told estimator finds a wall's relief (and
    its paint, hence the small gain) and sharper rims, and reads the objects themselves worse; mixed, both gain
    (docs/BENCHMARKS.md, round 20: rules OW, OW3–OW5)."""

    size: ReadSide = Field(description="The long side the walls are read at.")
    wall_relief: FiniteFloat = Field(
        ge=0,
        le=1,
        description="`wall_relief` of the closer read (`lasagna.compose.surface.calm_walls`): the walls' slopes times "
        "this, so a painted wall read closer stays flat.",
    )
    keep_rims: int = Field(
        0,
        ge=0,
        le=8,
        strict=True,
        description="The working-size read's silhouette probability dilated by this many working-size pixels (a "
        "max over a (2r + 1)² window) before the mix, so the band round each object, where the closer read draws a "
        "sharper rim on the wall's side of the outline too, keeps the working-size read; 0: the probability as read.",
    )
    gate: Literal["own", "working"] = Field(
        "own",
        description="Which silhouette calms the closer read's walls: 'own', the closer read's (as `wall_relief` gates "
        "any read); 'working', the working-size read's, so what the closer read alone takes for an object (a sky "
        "between thin structures, a lawn) is calmed where the working-size read sees a wall.",
    )
    rims_by_closer: bool = Field(
        False,
        description="Within that band (the dilated probability above the plain one), keep the working-size read only "
        "where the closer read's own silhouette probability is below 1/2 (it sees a wall there), and take the closer "
        "read's sharper rim where it sees an object; false: the whole band keeps the working-size read.",
    )


class ToldSurface(StrictModel):
    """What a surface layer reads when the user tells it the source light (``--from``): its own estimator (one
    trained to read the light it is given, ``train-surface --light-input``), that estimator's wall gates and the size
    its refinement works at. A light the user knows need not be fitted, so the estimator that reads best told it is
    not the one that reads best alone (docs/BENCHMARKS.md, round 18: rules TL), and a surface read told its light
    is refined best at another size than one whose light was fitted (round 22: rule RS)."""

    estimator: NameOrPath = Field(
        description="The surface estimator a surface layer told its source light reads: a catalogue name, or a path "
        "(with '/') relative to this preset's folder. It reads the image and the light it is told."
    )
    wall_relief: FiniteFloat = Field(
        1.0,
        ge=0,
        le=1,
        description="`wall_relief` for this estimator's surface layer (the preset's `surface.wall_relief` applies "
        "when the light is not told).",
    )
    closer_walls: CloserWalls | None = Field(
        None,
        description="`closer_walls` for this estimator's surface layer (the preset's `surface.closer_walls` applies "
        "when the light is not told).",
    )
    refine_size: ReadSide | None = Field(
        None,
        description="`refine_size` for this estimator's surface layer (the long side its refinement works at); "
        "null: the preset's `surface.refine_size`, as when the light is not told.",
    )


class SurfaceDefaults(StrictModel):
    """How a preset makes a surface layer: its estimator, and the multi-light score distillation after it."""

    estimator: NameOrPath = Field(
        description="The surface estimator (`lasagna train-surface`): a catalogue name, or a path (with '/') relative "
        "to this preset's folder."
    )
    refine_steps: int = Field(
        0,
        ge=0,
        le=MAX_DISTILL_STEPS,
        strict=True,
        description="Multi-light score-distillation steps after the estimate (0: the estimate as it is).",
    )
    lights_per_step: int = Field(4, ge=1, le=16, strict=True, description="Lights each refinement step scores.")
    lr: FiniteFloat = Field(0.01, gt=0, description="Adam learning rate of the height field's refinement.")
    anchor: FiniteFloat = Field(
        1.0, ge=0, description="Weight of ‖h − h₀‖², which keeps the refinement near the estimate."
    )
    refine_size: ReadSide | None = Field(
        None,
        description="The long side the refinement works at: the estimate enlarged to it, scored on the whole image "
        "for `distill.whole_fraction` of the steps and on crops of the prior's size at native resolution after; "
        "None: the estimate's working size.",
    )
    refine_lock: FiniteFloat = Field(
        0.0,
        ge=0,
        le=1,
        description="The refinement's correction to the estimate without its low frequencies: a Gaussian of this "
        "width (a fraction of the working size's long side) removed from it, so the estimate's large shape is kept "
        "(`lasagna.distill.surface`); 0: the correction as it is.",
    )
    refine_smooth: FiniteFloat = Field(
        0.0,
        ge=0,
        le=4,
        description="The refinement's correction also blurred by a Gaussian of this width in the pixels it works at "
        "(`lasagna.distill.surface`), so no relief finer than those pixels is made (enlarged to a photograph's "
        "size, it shows as blocks); 0: none removed.",
    )
    refine_objects: bool = Field(
        False,
        strict=True,
        description="The refinement acts on the objects only: its correction weighted by the estimator's silhouette "
        "probability (walls keep the estimate). Needs an estimator with a silhouette head.",
    )
    light_calibration: tuple[FiniteFloat, FiniteFloat] | None = Field(
        None,
        description="(offset, gain): a lit estimator's fitted source light's elevation θ (degrees) mapped to "
        "offset + gain·θ (`lasagna.compose.surface.calibrate_elevation`), the line fitted on `train` by "
        "benchmarks/light_calibration.py; None: as fitted. It applies to the surface layer (the free layer's "
        "surface start keeps the light as fitted); a light given with --from is used as given.",
    )
    source_elevation: SourceElevation = Field(
        "fit",
        description="The surface layer's fitted source light's elevation: 'fit', as the least-squares fit through "
        "the surface gives it; 'walls', the elevation that lights a flat wall to the estimated source shading's mean "
        "over the walls (pixels weighted by 1 − the silhouette probability; needs a silhouette head), the azimuth "
        "the fit's. `light_calibration` then maps it. The free layer's surface start keeps the fit.",
    )
    refine_light: bool = Field(
        False,
        strict=True,
        description="Refine a lit input's fitted source light with the surface (`refine_steps` > 0; a light the "
        "user gives with --from is kept as given).",
    )
    working_size: int = Field(32, ge=8, le=4096, strict=True, description="The long side the surface is estimated at.")
    dome_weight: FiniteFloat = Field(
        0.0,
        ge=0,
        le=1,
        description="Weight of the dome prior (the estimated silhouettes inflated into domes) mixed into the "
        "estimated normals; 0: the estimate alone. Needs an estimator with a silhouette head.",
    )
    dome_height: FiniteFloat = Field(
        1.0, gt=0, le=4, description="The domes' height as a fraction of a round dome's (a disc inflates to a sphere)."
    )
    symmetry: Symmetry = Field(
        "none",
        description="The estimator's symmetry ensemble (`SurfaceEstimator.estimate`): 'none', one estimate; "
        "'mirrors', the image and its three mirror images estimated, each mapped back, averaged; 'dihedral', those "
        "and their transposes (all eight symmetries of the square).",
    )
    flat_walls: FiniteFloat = Field(
        0.0,
        ge=0,
        le=1,
        description="The walls' large-scale tilt removed from the estimate (`lasagna.compose.surface.flatten_walls`): "
        "the slopes less their wall-weighted Gaussian mean of this width (a fraction of the working size's long side), "
        "walls weighted by 1 − the silhouette probability, so a painted gradient is not read as a tilted wall; 0: the "
        "estimate as it is. Applies to the surface layer and to a free layer's surface start. Needs an estimator with "
        "a silhouette head.",
    )
    wall_relief: FiniteFloat = Field(
        1.0,
        ge=0,
        le=1,
        description="A surface layer's walls' slopes times this (`lasagna.compose.surface.calm_walls`: each pixel's "
        "slopes times 1 − w + this·w, w = 1 − the silhouette probability eroded by one pixel so the objects' rims "
        "keep theirs), so a painted wall read as relief stays "
        "nearly flat while the objects keep theirs; 1: the estimate as it is. Applies to the surface layer, not to a "
        "free layer's surface start. Needs an estimator with a silhouette head.",
    )
    closer_walls: CloserWalls | None = Field(
        None,
        description="A second, closer read of the walls mixed into a surface layer's normals (`CloserWalls`); None: "
        "the working-size read alone. Applies to the surface layer, not to a free layer's surface start. Needs an "
        "estimator with a silhouette head.",
    )
    told: ToldSurface | None = Field(
        None,
        description="The estimator (and its wall gate) a surface layer reads when told its source light (`--from`); "
        "None: the same as when the light is fitted. The free layer's surface start and an untold surface layer read "
        "`estimator`.",
    )
    start_wall_relief: FiniteFloat = Field(
        1.0,
        ge=0,
        le=1,
        description="As `wall_relief`, for a free layer's surface start (`distill.start` 'surface'), before "
        "`start_relief` deepens it: a sky's clouds or a wall's paint read as relief are not deepened into the start; "
        "1: the estimate as it is. Needs an estimator with a silhouette head.",
    )
    start_relief: FiniteFloat = Field(
        1.0,
        gt=0,
        le=8,
        description="The relief gain of a free layer's surface start (`distill.start` 'surface'): the estimate's "
        "slopes times this (`lasagna.compose.surface.deepen_normals`), its source light fitted to the deepened "
        "surface. A surface layer (`layer_kind` 'surface') renders the estimate as it is.",
    )
    enlarge: SurfaceEnlarge = Field(
        "bicubic",
        description="How a surface layer's normals are enlarged from the working size to the image's: 'bicubic' "
        "(continuous slopes, `lasagna.compose.surface.enlarge_surface`); 'guided', the fast guided filter with the "
        "image's luma as guide (`lasagna.compose.resample.guided_upsample`), so the relief's edges follow the image's "
        "instead of the working size's pixel grid; 'bilateral', joint bilateral upsampling with the luma as guide "
        "(`lasagna.compose.resample.joint_bilateral_upsample`): each pixel a weighted mean of the nearby working-size "
        "normals of similar luma, so an object's rim stops at its edge without the guide's texture copied in.",
    )


class Preset(StrictModel):
    """A learned-layer preset, the content of ``layers/<name>/preset.json``."""

    model_config = ConfigDict(json_schema_extra=RANGE_FOR_BLEND_SCHEMA)

    format: Literal["lasagna.preset"] = Field(description="Always 'lasagna.preset'.")
    version: Literal[1] = Field(description="Preset format version; this is version 1.")
    name: LayerId = Field(description="The preset's name; equals its folder name in a catalogue.")
    description: str = Field(min_length=1, description="What the layer does, one or two sentences.")
    blend: Blend = Field(description="The blend the layer is composed with.")
    channels: Literal[1, 3, 4] = Field(description="1: gray (a multiplier broadcast over RGB), 3: RGB, 4: RGBA.")
    range: Range = Field(UNIT_RANGE, description="[lo, hi] of the layer's values; not [0, 1] only for multiply/plus.")
    prior: NameOrPath = Field(
        description="The conditional prior: a registered name, or a path (with '/') relative to this preset's folder."
    )
    corrective: NameOrPath | None = Field(None, description="LMC-SDS corrective b-hat, named like the prior.")
    vocabulary: tuple[str, ...] = Field(
        min_length=1, json_schema_extra={"uniqueItems": True}, description="Condition labels the prior was trained on."
    )
    prompt: str = Field(description="Prompt template with one '{label}' placeholder.")
    distill: DistillDefaults = Field(DistillDefaults(), description="Default distillation settings.")
    diffusers: DiffusersOptions | None = Field(
        None, description="How a diffusers prior is loaded and run (dtype, variant, offload, …); None: the defaults."
    )
    method: Method | None = Field(
        None,
        description="How `lasagna edit` makes the layer when not told: 'amortised' (the preset's generator, then "
        "refine_steps per-image steps) or 'per-image' (distill.steps steps from the identity). None: amortised when "
        "the preset has a generator, else per-image.",
    )
    refine_steps: int = Field(
        0,
        ge=0,
        le=MAX_DISTILL_STEPS,
        strict=True,
        description="Per-image steps after the amortised pass, by default (0: the generator's layer as it is).",
    )
    task: WorldTask | None = Field(
        None,
        description="The world task `lasagna train-layer` trains the preset's generator on: 'relight' (shading "
        "multiplied onto an albedo), 'relit' (a luminosity ratio multiplied onto an image already lit), 'colorize', "
        "'light'. None: the blend's task (multiply: relight, normal: colorize, plus: light).",
    )
    working_size: int | None = Field(
        None,
        ge=8,
        le=4096,
        strict=True,
        description="The layer is made with its long side at this size (the base reduced by an antialiasing filter) "
        "and enlarged bilinearly to the image's: the size the generator was trained at, so quality does not depend on "
        "the image's resolution. None: made at the image's own size.",
    )

    luminance: Luminance = Field(
        "free",
        description="'base': colour over luminance — the layer is made from the base's Rec. 709 luma (a gray image, as "
        "the colorize task trains) and its colour carries that luma, so the composite keeps the input's luminance "
        "and only its colour changes (blend normal only). 'free': the layer's values are its own.",
    )

    enlarge: Enlarge = Field(
        "bilinear",
        description="How the layer made at the working size is enlarged to the image's: 'bilinear', or 'guided' — the "
        "fast guided filter with the base's full-size luma as guide (radius and ε of lasagna.compose.resample), so "
        "its edges follow the image's. For luminance 'free' layers (a colour-over-luminance layer has its own rule).",
    )

    layer_kind: LayerKind = Field(
        "free",
        description="The layer `lasagna edit` makes when not told: 'free' (a per-pixel multiplier) or 'surface' (a "
        "surface lit by the condition's light; needs `surface`).",
    )
    surface: SurfaceDefaults | None = Field(None, description="How the surface route makes its layer.")

    @field_validator("vocabulary")
    @classmethod
    def _labels(cls, labels: tuple[str, ...]) -> tuple[str, ...]:
        for i, label in enumerate(labels):
            if not label or label != label.strip():
                raise RuleError(
                    f"label {label!r} is empty or has outer spaces; labels are trimmed, non-empty", loc=(i,)
                )
            if label in labels[:i]:
                raise RuleError(f"label {label!r} repeats; vocabulary labels are unique", loc=(i,))
        return labels

    @field_validator("prompt")
    @classmethod
    def _template(cls, prompt: str) -> str:
        try:
            fields = [f for _, f, _, _ in string.Formatter().parse(prompt) if f is not None]
        except ValueError as exc:
            raise RuleError(f"prompt {prompt!r} is not a valid template ({exc}); use {{label}} once") from None
        if fields != ["label"]:
            raise RuleError(f"prompt {prompt!r} has placeholders {fields}; the rule is exactly one '{{label}}'")
        return prompt

    @model_validator(mode="after")
    def _rules(self) -> Preset:
        check_range_for_blend(self.range, self.blend)
        if self.distill.loss == "lmc-sds" and self.corrective is None:
            raise RuleError(
                "loss 'lmc-sds' needs a corrective (b-hat of LMC-SDS eq. 10); name one", loc=("corrective",)
            )
        if self.surface is not None and (self.blend not in ("multiply", "multiply-luminosity") or self.channels != 1):
            raise RuleError(
                f"a surface renders a 1-channel multiplier; preset {self.name!r} has blend {self.blend!r} and "
                f"{self.channels} channel(s): expected blend multiply, channels 1 for `surface`",
                loc=("surface",),
            )
        if self.distill.start == "surface" and self.surface is None:
            raise RuleError(
                f"preset {self.name!r} starts its free layer from a surface (distill.start 'surface') but names no "
                "surface estimator: expected `surface`",
                loc=("distill", "start"),
            )
        if self.distill.lock == "planar" and self.distill.start != "surface":
            raise RuleError(
                f"preset {self.name!r} locks its free layer's tilt (distill.lock 'planar') but starts it from the "
                f"{self.distill.start}: the lock keeps a surface start's direction; expected distill.start 'surface'",
                loc=("distill", "lock"),
            )
        if self.distill.objects_only and self.distill.start != "surface":
            raise RuleError(
                f"preset {self.name!r} keeps its free layer's correction to the objects (distill.objects_only) but "
                f"starts it from the {self.distill.start}: walls keep a surface start; expected distill.start "
                "'surface'",
                loc=("distill", "objects_only"),
            )
        if self.luminance == "base" and self.blend not in ("normal", "alpha-linear"):
            raise RuleError(
                f"luminance 'base' lays colour over the base's luminance with alpha-linear blending; preset "
                f"{self.name!r} has blend {self.blend!r}: expected blend normal",
                loc=("luminance",),
            )
        if self.enlarge == "guided" and self.luminance == "base":
            raise RuleError(
                f"preset {self.name!r} has luminance 'base', whose colour is enlarged by its own guided rule; "
                "expected enlarge 'bilinear' (the default) with it",
                loc=("enlarge",),
            )
        if self.layer_kind == "surface" and self.surface is None:
            raise RuleError("layer_kind 'surface' needs `surface` (its estimator); name one", loc=("surface",))
        return self

    @property
    def world_task(self) -> str:
        """The world task the generator trains on: ``task``, else the blend's (``TASK_FOR_BLEND``)."""
        return self.task or TASK_FOR_BLEND[self.blend]

    @property
    def takes_directions(self) -> bool:
        """Whether the vocabulary is light directions (the eight named lights): then a condition may also be any
        direction ``az=…,el=…`` (``lasagna.document.condition``), which a direction-conditioned prior renders."""
        return bool(self.vocabulary) and set(self.vocabulary) <= set(NAMED_DIRECTIONS)

    def prompt_for(self, label: str) -> str:
        """The prompt for ``label``; ``ConditionError`` if it is not in the vocabulary (nor, for a preset that
        ``takes_directions``, an ``az=…,el=…`` direction)."""
        if label not in self.vocabulary and self.takes_directions and isinstance(label, str) and "=" in label:
            parse_direction(label)  # ConditionError saying what a direction is
            return self.prompt.format(label=label)
        if label not in self.vocabulary:
            raise ConditionError(
                f"label {label!r} is not in preset {self.name!r}'s vocabulary; expected one of "
                f"{', '.join(self.vocabulary)}",
                "condition.label",
            )
        return self.prompt.format(label=label)

    def to_json(self) -> str:
        """The preset.json text: every field, canonical names, stable layout."""
        return dumps(self.model_dump(mode="json")) + "\n"

    @classmethod
    def from_dict(cls, data: Any, where: str | None = None) -> Preset:
        try:
            return cls.model_validate(data)
        except ValidationError as err:
            raise document_error(err, where, cls) from None

    @classmethod
    def from_json(cls, text: str, where: str = "preset.json") -> Preset:
        return cls.from_dict(parse_json(text, where), where)


def load_preset(path: str | os.PathLike) -> Preset:
    """Read a preset from ``preset.json`` or from the folder holding it; its name must match the folder."""
    file = Path(path)
    file = file / "preset.json" if file.is_dir() else file
    text = read_json_text(file, "a preset.json file")
    preset = Preset.from_json(text, str(file))
    if file.name == "preset.json" and file.parent.name != preset.name:
        raise DocumentError(
            f"name {preset.name!r} differs from its folder {file.parent.name!r}; a preset lives in layers/<name>/",
            f"{file}: name",
        )
    return preset


def user_catalogue() -> Path:
    """Where ``lasagna prior add`` writes when ``$LASAGNA_LAYERS`` names no folder:
    ``$XDG_DATA_HOME/lasagna/layers`` (``~/.local/share/lasagna/layers`` without it), searched after
    ``$LASAGNA_LAYERS``'s folders."""
    data = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(data) / "lasagna" / "layers"


def default_catalogues() -> list[Path]:
    """Catalogue folders searched for preset names: ``$LASAGNA_LAYERS`` (os.pathsep-separated), the user's
    catalogue (``user_catalogue()``, when it exists), then the repository's ``layers/`` when running from a
    checkout."""
    dirs = [Path(p) for p in os.environ.get("LASAGNA_LAYERS", "").split(os.pathsep) if p]
    user = user_catalogue()
    if user.is_dir():
        dirs.append(user)
    root = Path(__file__).resolve().parents[2]
    # A checkout has pyproject.toml beside layers/; an installed package's parents[2] is
    # site-packages, whose layers/ (if any) belongs to someone else. The installed copy of the
    # catalogue is lasagna/_layers (see pyproject.toml).
    checkout = root / "layers" if (root / "pyproject.toml").is_file() else None
    installed = Path(__file__).resolve().parents[1] / "_layers"
    # In a checkout lasagna/_layers holds only its PACKAGING.md placeholder: listed only with entries.
    if not (installed.is_dir() and any(p.is_dir() for p in installed.iterdir())):
        installed = None
    return dirs + [d for d in (checkout, installed) if d is not None and d.is_dir()]
