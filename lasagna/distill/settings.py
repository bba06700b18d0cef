"""The resolved settings of a per-image distillation run (saved beside its checkpoints and results).

``DistillSettings.from_preset(preset, **overrides)`` takes a preset's layer (blend, channels, range)
and its ``distill`` defaults (loss, ω, steps, lr, t interval, seed), then applies the caller's
overrides; every field is validated, unknown ones are refused.

Defaults and their sources:

* loss ``lmc-sds`` (the issue's default; a preset's own ``distill.loss`` wins when a preset is
  given), ω = 1, 150 Adam steps at lr 0.03 (the CPU prototype's free shading layer);
* learning rate: cosine decay to ``lr_final``·lr over the run (LMC-SDS editing: "Cosine decay of 0.8
  over all steps"); with patches this is the "decaying learning rate" of the patch phase;
* weights: the score at 1 and the L2 to the identity edit from 0.1 falling to 0 over the first
  ``steps``/3 steps (``per_image_weights``), the LMC-SDS network recipe's cosine shape, scaled to a
  per-image run. (Adam is blind to a common factor of both terms, so only their ratio matters: it
  starts near the paper's editing weight of 0.1 and releases the edit; the layer's blend already
  keeps the content, so no lasting pull to the input is needed.)
* patches (images larger than the prior): the whole image, downsampled, for the first
  ``whole_fraction`` of the steps (LMC-SDS editing: 200 of 500), then ``per_step`` random crops of the
  prior's size per image per step;
* early stopping (``EarlyStop``, see ``per_image.py``): on, checked in the last phase only.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_serializer, model_validator

from lasagna.distill.objective import ConditionImage
from lasagna.distill.schedules import Ramp, Weights
from lasagna.document.preset import Aspect, FreeLock, FreeStart, LossName, SurfaceDefaults
from lasagna.errors import describe_validation_error
from lasagna.generators.layer import LayerSpec
from lasagna.limits import MAX_CROPS_PER_STEP, MAX_DISTILL_STEPS, MAX_PARTICLES


class PatchConfig(BaseModel):
    """The LMC-SDS strategy for images larger than the prior (Sec. 5 and the supplementary)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    whole_fraction: float = Field(
        0.4, ge=0.0, le=1.0, description="Fraction of the steps on the whole image, downsampled."
    )
    per_step: int = Field(
        1,
        ge=1,
        le=MAX_CROPS_PER_STEP,
        description="Random crops of the prior's size per image per step (LMC-SDS synthesis: 2).",
    )


class EarlyStop(BaseModel):
    """Stop when, over the last ``window`` steps, neither the score's gradient norm nor the layer's
    change per unit learning rate fell by more than ``rtol`` against the ``window`` steps before."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    window: int = Field(20, ge=2, le=MAX_DISTILL_STEPS)
    min_steps: int = Field(60, ge=0, le=MAX_DISTILL_STEPS, description="No stop before this many steps of the run.")
    rtol: float = Field(0.02, ge=0.0, lt=1.0)


def per_image_weights(steps: int) -> Weights:
    """The default per-image weights for a run of ``steps`` steps (see the module docstring)."""
    return Weights(score=Ramp.constant(1.0), reg=Ramp(start=0.1, end=0.0, steps=max(steps // 3, 1)))


class DistillSettings(BaseModel):
    """Everything that determines a per-image distillation run, except the image, condition and prior."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    layer: LayerSpec
    loss: LossName = "lmc-sds"
    loss_options: dict[str, Any] = Field(default_factory=dict, description="Extra options of the loss's Options model.")
    guidance: float = Field(1.0, gt=0.0, description="ω in ε_u + ω(ε_c − ε_u).")
    steps: int = Field(150, ge=1, le=MAX_DISTILL_STEPS, description="Steps (a document cannot ask for more).")
    lr: float = Field(0.03, gt=0.0, description="Adam learning rate at the first step.")
    lr_final: float = Field(0.8, gt=0.0, le=1.0, description="lr multiplier reached at the last step (cosine).")
    grad_clip: float | None = Field(None, gt=0.0, description="Clip the parameters' global gradient norm to this.")
    t_min: float = Field(0.02, ge=0.0, le=1.0)
    t_max: float = Field(0.98, ge=0.0, le=1.0)
    seed: int = Field(0, ge=0)
    particles: int = Field(
        1,
        ge=1,
        le=MAX_PARTICLES,
        description="Layers per image with their own noise draws, averaged at the end (per_image.py).",
    )
    particle_mirrors: bool = Field(
        False, description="Particle j sees the image and its light mirrored by PARTICLE_MIRRORS[j % 4] (per_image.py)."
    )
    weights: Weights | None = Field(None, description="Objective weights; None = per_image_weights(steps).")
    patches: PatchConfig = PatchConfig()
    early_stop: EarlyStop | None = EarlyStop()
    condition_image: ConditionImage = "auto"
    # Settings stored before ``aspect`` existed were made by stretching: that stays their meaning (a preset's
    # default, which new edits take, is letterbox).
    aspect: Aspect = Field("stretch", description="A view of another aspect than the prior's: letterbox or stretch.")
    checkpoint_every: int = Field(
        50, ge=1, le=MAX_DISTILL_STEPS, description="Steps between checkpoints when a checkpoint folder is given."
    )
    start: FreeStart = Field(
        "identity",
        description="Where a free layer starts: the identity edit, or the preset's surface estimate under the "
        "condition (lasagna.learned: a free residual on a surface).",
    )
    lock: FreeLock = Field(
        "none",
        description="What of its start a free layer keeps after the steps: nothing, or its planar trend "
        "(lasagna.learned.planar_lock).",
    )
    objects_only: bool = Field(
        False,
        description="A surface start's correction kept on the objects only (log(layer/start) times the estimator's "
        "silhouette probability: lasagna.learned.objects_lock).",
    )
    start_surface: SurfaceDefaults | None = Field(
        None,
        description="How a surface start was made (``start`` 'surface'): the preset's `surface` fields when the layer "
        "was made — estimator, working size, dome prior, symmetry ensemble, start relief — so the layer is made again "
        "from its record, not from a preset changed since. None: the preset's (settings recorded before).",
    )

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # "identity" is every free layer's start before surfaces: left out, so settings recorded before read the same.
        data = handler(self)
        if data.get("start") == "identity":
            del data["start"]
        if data.get("lock") == "none":  # likewise: no lock is every layer's before locks
            del data["lock"]
        if data.get("objects_only") is False:  # likewise: every layer's before the objects-only correction
            del data["objects_only"]
        if data.get("start_surface") is None:  # likewise: settings recorded before surface starts were recorded
            data.pop("start_surface", None)
        return data

    @model_validator(mode="after")
    def _check(self) -> DistillSettings:
        if self.t_min > self.t_max:
            raise ValueError(f"t_min {self.t_min} > t_max {self.t_max}; expected t_min <= t_max")
        if self.objects_only and self.start != "surface":
            raise ValueError("objects_only keeps a surface start on the walls; expected start 'surface'")
        return self

    def resolved_weights(self) -> Weights:
        return self.weights if self.weights is not None else per_image_weights(self.steps)

    @classmethod
    def from_preset(cls, preset, **overrides: Any) -> DistillSettings:
        """A preset's layer and distillation defaults, with ``overrides`` (None values ignored) applied."""
        d = preset.distill
        data: dict[str, Any] = {
            "layer": LayerSpec.from_preset(preset),
            "loss": d.loss,
            "guidance": d.guidance,
            "steps": d.steps,
            "lr": d.lr,
            "t_min": d.t_min,
            "t_max": d.t_max,
            "seed": d.seed,
            "particles": d.particles,
            "particle_mirrors": d.particle_mirrors,
            "patches": PatchConfig(whole_fraction=d.whole_fraction),
            "aspect": d.aspect,
            "start": d.start,
            "lock": d.lock,
            "objects_only": d.objects_only,
            "start_surface": preset.surface if d.start == "surface" else None,
        }
        return cls.parse({**data, **{k: v for k, v in overrides.items() if v is not None}})

    def with_overrides(self, **overrides: Any) -> DistillSettings:
        """A copy with ``overrides`` (None values ignored), re-validated."""
        return self.parse({**self.model_dump(), **{k: v for k, v in overrides.items() if v is not None}})

    @classmethod
    def parse(cls, data: dict[str, Any], where: str = "settings") -> DistillSettings:
        """Validate ``data``; a bad field is a one-line ``LasagnaError`` naming it."""
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise describe_validation_error(exc, prefix=where) from None
