"""Measuring a bundled prior against the world's ground truth (the numbers of its model card).

* ``denoising_error``: mean squared error of x̂₀ against the clean image, per timestep bucket — where
  along t the prior is accurate (the CPU prototype's ε-prediction failure showed up at t → T).
* ``sample_quality``: DDIM samples conditioned on a scene's conditioning image and label, against the
  true image under that label: PSNR per label, for each guidance weight ω (the guidance sweep).

PSNR is over [0, 1] images: 10·log10(1 / MSE), averaged per image then over images.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence

import torch

from lasagna.priors.base import Condition, Prior
from lasagna.priors.ddim import ddim_sample
from lasagna.priors.nn import randn

PSNR_FLOOR_MSE = 1e-10  # an exact match is reported as 100 dB rather than +inf


def psnr_db(mse: torch.Tensor | float, floor: float = PSNR_FLOOR_MSE) -> torch.Tensor:
    """PSNR in dB (peak 1) of a mean squared error of images in [0, 1]: 10·log10(1 / MSE), float64, the MSE
    floored at ``floor`` (an exact match is a finite number). The one PSNR of the package, its benchmarks and
    its trainers."""
    return -10 * torch.log10(torch.as_tensor(mse, dtype=torch.float64).clamp_min(floor))


def psnr(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-image PSNR (B,) of images in [0, 1]."""
    return psnr_db((a.double() - b.double()).pow(2).flatten(1).mean(1))


@torch.no_grad()
def denoising_error(
    prior: Prior,
    images: torch.Tensor,
    labels: Sequence[str],
    cond_image: torch.Tensor | None,
    t_values: Sequence[float] = (0.02, 0.1, 0.25, 0.5, 0.75, 0.9, 0.98),
    seed: int = 0,
) -> dict[float, float]:
    """MSE of the conditional x̂₀ (in [0, 1] units) per continuous t, averaged over ``images``."""
    rng = torch.Generator().manual_seed(seed)
    z = prior.encode(images)
    out = {}
    for u in t_values:
        t = prior.schedule.continuous_to_index(torch.full((z.shape[0],), float(u)))
        z_t = prior.schedule.add_noise(z, randn(tuple(z.shape), rng, z.device, z.dtype), t)
        eps = prior.predict(z_t, t, Condition(list(labels), image=cond_image), branches=("cond",)).eps["cond"]
        x0 = prior.decode(prior.schedule.x0_from_eps(z_t, eps, t))
        out[float(u)] = float((x0 - images).pow(2).mean())
    return out


@torch.no_grad()
def sample_quality(
    prior: Prior,
    images: torch.Tensor,
    labels: Sequence[str],
    cond_image: torch.Tensor | None,
    omegas: Sequence[float] = (1.0, 3.0, 7.5),
    steps: int = 50,
    seed: int = 0,
    chunk: int = 64,
) -> dict[float, dict[str, float]]:
    """{ω: {label: mean PSNR, "all": mean PSNR}} of DDIM-``steps`` samples against ``images``."""
    result: dict[float, dict[str, float]] = {}
    for omega in omegas:
        scores: dict[str, list[float]] = defaultdict(list)
        for i in range(0, images.shape[0], chunk):
            sl = slice(i, i + chunk)
            rng = torch.Generator().manual_seed(seed + i)
            img = None if cond_image is None else cond_image[sl]
            labs = list(labels[sl])
            res = ddim_sample(prior, Condition(labs, image=img), steps=steps, omega=omega, rng=rng, batch=len(labs))
            for lab, p in zip(labs, psnr(res.image.clamp(0, 1), images[sl]).tolist()):
                scores[lab].append(p)
        per = {lab: sum(v) / len(v) for lab, v in sorted(scores.items())}
        allv = [p for v in scores.values() for p in v]
        per["all"] = sum(allv) / len(allv) if allv else math.nan
        result[float(omega)] = per
    return result
