"""Score Distillation Sampling (Poole et al. 2022, "DreamFusion", eq. 3), split as LMC-SDS eq. 6.

For the clean image z (the encoded composite), t ~ U(t_min, t_max), ε ~ N(0, I),
z_t = √ᾱ_t z + √(1 − ᾱ_t) ε:

    ∇_z L_SDS = w(t) (ε̂^ω(z_t, y, t) − ε),       ε̂^ω = ε_u + ω(ε_c − ε_u)           (eq. 3, 5)
              = w(t) [ω(ε_c − ε_u)  +  (ε_u − ε)]
                       └─ L_cond ─┘    └ L_proj ┘                                    (eq. 6b, 6c)

The Jacobian of the denoiser is omitted (eq. 2 → 3) and ∂z_t/∂z = √ᾱ_t is absorbed into w(t)
(DreamFusion, footnote to eq. 3). ``diagnostics.components`` holds the two terms, already weighted,
so ``grad = components["cond"] + components["proj"]``.

Default weighting: w(t) = 1 − ᾱ_t (DreamFusion's σ_t²); "uniform" and √ᾱ_t(1 − ᾱ_t) are options.
One batched prior pass per step (cond and uncond branches together). At ω = 1 the unconditional branch cancels
(ε̂¹ = ε_c, eq. 5), so the pass is of the conditional branch alone — half the batch, the work a guidance of 1 does
not need — and ``components`` holds the one term ``"guided"`` = w(t)(ε_c − ε) (the same gradient, to rounding).
"""

from __future__ import annotations

import torch

from lasagna.losses.base import LossOptions, ScoreLoss, Terms, register_loss
from lasagna.losses.core import Weighting
from lasagna.priors.base import Condition, Prior
from lasagna.priors.nn import randn


class SDSOptions(LossOptions):
    weighting: Weighting = "1-alpha_bar"


@register_loss("sds")
class SDS(ScoreLoss):
    """DreamFusion's SDS with classifier-free guidance ω (see the module docstring)."""

    Options = SDSOptions

    def terms(
        self, z: torch.Tensor, t: torch.Tensor, prior: Prior, cond: Condition, omega: float, rng: torch.Generator | None
    ) -> Terms:
        eps = randn(tuple(z.shape), rng, z.device, z.dtype)
        z_t = prior.schedule.add_noise(z, eps, t)
        if omega == 1.0:  # ω(ε_c − ε_u) + (ε_u − ε) = ε_c − ε: no unconditional pass
            (e_c,) = prior.predict_many([(z_t, "cond")], t, cond)
            return Terms(components={"guided": e_c.to(z.dtype) - eps}, noise={"eps": eps})
        e_c, e_u = (e.to(z.dtype) for e in prior.predict_many([(z_t, "cond"), (z_t, "uncond")], t, cond))
        return Terms(components={"cond": omega * (e_c - e_u), "proj": e_u - eps}, noise={"eps": eps})
