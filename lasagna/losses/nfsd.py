"""Noise-Free Score Distillation (Katzir, Patashnik, Cohen-Or & Lischinski, ICLR 2024, eq. 11).

NFSD drops the noise term of SDS and replaces L_proj by a "domain" direction:

    ∇_z L_NFSD = w(t) [ ω δ_C + δ_D ]
    δ_C = ε_φ(z_t, y, t) − ε_φ(z_t, ∅, t)                       (the condition direction = L_cond/ω)
    δ_D = ε_φ(z_t, ∅, t)                          if t < 200   (small t: the unconditional
                                                                prediction is mostly domain signal)
        = ε_φ(z_t, ∅, t) − ε_φ(z_t, y_neg, t)    otherwise    (away from the negative condition)

In our CFG convention ε_u + ω(ε_c − ε_u) the paper's guidance scale s multiplies δ_C, so s = ω.

Interpretations:
* **t < 200** is the paper's rule for a T = 1000 schedule. We keep it as a fraction of the schedule,
  ``small_t_fraction = 0.2``: the mask is t_index < 0.2·T, i.e. exactly t < 200 for T = 1000. With
  the sampler's continuous t (index = round(t·(T − 1))) that is t < 199.5/999 ≈ 0.1997. The rule
  is applied per sample, as a mask: a batch mixes both regimes.
* **The negative condition** is ``cond.negative`` when given, else ``NFSDOptions.negative_label``
  (a label of the prior's vocabulary; the paper uses the prompt "unrealistic, blurry, low quality,
  out of focus, ugly, low contrast, dull, dark, low-resolution, gloomy"). Neither → an error.

The negative branch is evaluated for every sample (in the one batched pass with cond and uncond) and
masked afterwards; skipping it for small-t samples would cost a data-dependent batch size.
Weighting: w(t) = 1 − ᾱ_t by default (NFSD keeps DreamFusion's w(t)).
"""

from __future__ import annotations

import dataclasses

import torch
from pydantic import Field

from lasagna.errors import ConditionError
from lasagna.losses.base import LossOptions, ScoreLoss, Terms, register_loss
from lasagna.losses.core import Weighting, expand
from lasagna.priors.base import Condition, Prior
from lasagna.priors.nn import randn


class NFSDOptions(LossOptions):
    weighting: Weighting = "1-alpha_bar"
    negative_label: str | None = None
    small_t_fraction: float = Field(
        0.2, ge=0.0, le=1.0, description="δ_D = ε_u below this fraction of T (0.2 → t < 200 of 1000)"
    )


@register_loss("nfsd")
class NFSD(ScoreLoss):
    """Noise-Free Score Distillation (see the module docstring)."""

    Options = NFSDOptions

    def terms(
        self, z: torch.Tensor, t: torch.Tensor, prior: Prior, cond: Condition, omega: float, rng: torch.Generator | None
    ) -> Terms:
        if cond.negative is None:
            if self.options.negative_label is None:
                raise ConditionError(
                    "NFSD needs a negative condition: set condition.negative or NFSDOptions.negative_label",
                    "nfsd.negative",
                )
            cond = dataclasses.replace(cond, negative=self.options.negative_label)
        eps = randn(tuple(z.shape), rng, z.device, z.dtype)
        z_t = prior.schedule.add_noise(z, eps, t)
        e_c, e_u, e_n = (
            e.to(z.dtype) for e in prior.predict_many([(z_t, "cond"), (z_t, "uncond"), (z_t, "negative")], t, cond)
        )
        small = expand(t < self.options.small_t_fraction * prior.schedule.num_steps, z)  # (B, 1, 1, 1) bool
        delta_d = torch.where(small, e_u, e_u - e_n)
        return Terms(components={"cond": omega * (e_c - e_u), "domain": delta_d}, noise={"eps": eps})
