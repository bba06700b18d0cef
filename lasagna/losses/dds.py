"""Delta Denoising Score (Hertz, Aberman & Cohen-Or, ICCV 2023, eq. 5).

DDS edits a source image ẑ described by a source condition ŷ into z matching the target y by
subtracting the SDS gradient of the (image, condition) pair that is already right:

    ∇_z L_DDS = w(t) [ ε̂^ω(z_t, y, t) − ε̂^ω(ẑ_t, ŷ, t) ],   z_t = √ᾱ z + √(1−ᾱ) ε,  ẑ_t = √ᾱ ẑ + √(1−ᾱ) ε

with the SAME ε and t in both, and classifier-free guidance ω on both (as the DDS paper does). The
noise term ε of SDS cancels, and with it L_proj (LMC-SDS Sec. 3). ``components`` holds the two SDS
gradients: "target" = ε̂^ω(z_t, y) − ε and "source" = −(ε̂^ω(ẑ_t, ŷ) − ε).

How the source is supplied (our choice, documented):
* the source CONDITION ŷ is ``cond.negative`` — ``Condition`` reserves that field for "a second
  label" (NFSD's negative prompt, DDS's source prompt); without it the loss raises. For Lasagna's
  use (the base image described by the same lighting prompt) pass ``negative=cond.labels``.
* the source IMAGE ẑ (in [0, 1], like the composite) is ``DDS(source_image=...)`` or the
  attribute ``loss.source_image``; if unset, ``cond.image`` (the conditioning image — in Lasagna the
  base layer, which is the composite before any edit). Neither → an error.

All four denoiser evaluations (target cond/uncond, source cond/uncond) run in ONE batched pass.
Weighting: w(t) = 1 by default (the DDS paper has none).
"""

from __future__ import annotations

import torch

from lasagna.errors import ConditionError
from lasagna.losses.base import LossOptions, ScoreLoss, Terms, register_loss
from lasagna.losses.core import cfg
from lasagna.priors.base import Condition, Prior
from lasagna.priors.nn import randn


@register_loss("dds")
class DDS(ScoreLoss):
    """Delta Denoising Score (see the module docstring)."""

    Options = LossOptions

    def __init__(
        self, options: LossOptions | dict | None = None, source_image: torch.Tensor | None = None, **overrides
    ):
        super().__init__(options, **overrides)
        self.source_image = source_image

    def _source(self, z: torch.Tensor, prior: Prior, cond: Condition) -> torch.Tensor:
        src = self.source_image if self.source_image is not None else cond.image
        if src is None:
            raise ConditionError(
                "DDS needs a source image; set DDS(source_image=...) or give the condition an image", "dds.source_image"
            )
        if src.dim() != 4 or src.shape[0] not in (1, z.shape[0]):
            raise ConditionError(
                f"source image has shape {tuple(src.shape)}; expected (1 or {z.shape[0]}, C, H, W)", "dds.source_image"
            )
        with torch.no_grad():
            s = prior.encode(src.detach().to(device=z.device, dtype=z.dtype))
        if tuple(s.shape[1:]) != tuple(z.shape[1:]):
            raise ConditionError(
                f"source image encodes to {tuple(s.shape[1:])}; expected the composite's {tuple(z.shape[1:])}",
                "dds.source_image",
            )
        return s.expand_as(z)

    def terms(
        self, z: torch.Tensor, t: torch.Tensor, prior: Prior, cond: Condition, omega: float, rng: torch.Generator | None
    ) -> Terms:
        if cond.negative is None:
            raise ConditionError(
                "DDS needs the source condition ŷ in condition.negative (the label describing the source image); "
                "got None",
                "dds.condition.negative",
            )
        src = self._source(z, prior, cond)
        eps = randn(tuple(z.shape), rng, z.device, z.dtype)
        z_t = prior.schedule.add_noise(z, eps, t)
        s_t = prior.schedule.add_noise(src, eps, t)
        # The source condition travels as the "negative" branch; the unconditional branches are shared.
        e_c, e_u, s_c, s_u = (
            e.to(z.dtype)
            for e in prior.predict_many([(z_t, "cond"), (z_t, "uncond"), (s_t, "negative"), (s_t, "uncond")], t, cond)
        )
        target = cfg(e_u, e_c, omega) - eps
        source = cfg(s_u, s_c, omega) - eps
        return Terms(components={"target": target, "source": -source}, noise={"eps": eps})
