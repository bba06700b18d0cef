"""Distillation: learned edit layers from a conditional prior, through the composite (Lasagna, LMC-SDS).

- ``objective``   the shared piece: composite → view at the prior's size → score loss, plus the
                  scheduled L2 to the identity edit (``ScoreObjective``, ``build_loss``);
- ``schedules``   cosine ramps of the loss weights (``Ramp``, ``Weights``) and the cosine lr decay;
- ``settings``    ``DistillSettings`` (patches, early stopping), resolved from a preset;
- ``per_image``   ``distill_image(base, preset, prior, ...) -> DistillResult``.

Amortised distillation (one generator for every image) is a trainer: ``lasagna.training.generator``.
"""

from lasagna.distill.objective import (
    ObjectiveOutput,
    ScoreObjective,
    build_loss,
    conditioning_image,
    crop,
    draw_patches,
    prior_image_size,
    resize,
)
from lasagna.distill.per_image import DistillResult, converged, distill_image, resolve_settings
from lasagna.distill.schedules import Ramp, Weights, cosine_lr
from lasagna.distill.settings import DistillSettings, EarlyStop, PatchConfig, per_image_weights

__all__ = [
    "ObjectiveOutput",
    "ScoreObjective",
    "build_loss",
    "conditioning_image",
    "crop",
    "draw_patches",
    "prior_image_size",
    "resize",
    "DistillResult",
    "converged",
    "distill_image",
    "resolve_settings",
    "Ramp",
    "Weights",
    "cosine_lr",
    "DistillSettings",
    "EarlyStop",
    "PatchConfig",
    "per_image_weights",
]
