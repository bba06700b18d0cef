"""DDIM sampling (Song, Meng & Ermon 2021, "Denoising Diffusion Implicit Models", eq. 12) for any ``Prior``.

One step from t to the previous sampled timestep s (ᾱ_s = 1 after the last step)::

    ε̂   = ε_u + ω (ε_c − ε_u)                     one CFG convention (cond and uncond in ONE pass)
    x̂₀  = (z_t − √(1 − ᾱ_t) ε̂) / √ᾱ_t             "predicted x₀"
    σ_t = η √((1 − ᾱ_s)/(1 − ᾱ_t)) √(1 − ᾱ_t/ᾱ_s)  eq. 16; η = 0 is deterministic DDIM, η = 1 DDPM
    z_s = √ᾱ_s x̂₀ + √(1 − ᾱ_s − σ_t²) ε̂ + σ_t ξ,  ξ ~ N(0, I)

Used for baselines and checks (the distillation losses never sample). Step coefficients are computed
from the schedule's float64 ᾱ table as Python floats, so only the tensor arithmetic is float32.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from lasagna.priors.base import Condition, Prior, cfg
from lasagna.priors.nn import randn


@dataclass
class DDIMResult:
    """``z``: the sample in the prior's space (B, C, h, w); ``image``: ``prior.decode(z)`` clamped to [0, 1]
    (None when ``decode=False``)."""

    z: torch.Tensor
    image: torch.Tensor | None


def ddim_timesteps(num_train_steps: int, steps: int) -> list[int]:
    """``steps`` integer timesteps evenly spaced over [0, T − 1], descending, always starting at T − 1."""
    if not 1 <= steps <= num_train_steps:
        raise ValueError(f"ddim: steps must be in [1, {num_train_steps}], got {steps}")
    if steps == 1:
        return [num_train_steps - 1]
    grid = [round(i * (num_train_steps - 1) / (steps - 1)) for i in range(steps)]
    return sorted(set(grid), reverse=True)


def _batch_size(cond: Condition, batch: int | None, z_T: torch.Tensor | None) -> int:
    sizes = set()
    if z_T is not None:
        sizes.add(z_T.shape[0])
    if cond.image is not None:
        sizes.add(cond.image.shape[0])
    if not isinstance(cond.labels, str) and len(cond.labels) != 1:
        sizes.add(len(cond.labels))
    if batch is not None:
        sizes.add(batch)
    if len(sizes) > 1:
        raise ValueError(
            f"ddim: conflicting batch sizes {sorted(sizes)} from batch=, z_T, condition.labels and condition.image"
        )
    return sizes.pop() if sizes else 1


def _device(prior: Prior, cond: Condition) -> torch.device:
    if cond.image is not None:
        return cond.image.device
    p = next(iter(prior.parameters()), None)
    return p.device if p is not None else torch.device("cpu")


def guided_eps(prior: Prior, z_t: torch.Tensor, t: torch.Tensor, cond: Condition, omega: float) -> torch.Tensor:
    """ε_u + ω(ε_c − ε_u) from one batched pass; ω = 1 needs only the conditional branch, ω = 0 only
    the unconditional one (no wasted network evaluations)."""
    if omega == 1.0:
        return prior.predict(z_t, t, cond, branches=("cond",)).eps["cond"].to(z_t.dtype)
    if omega == 0.0:
        return prior.predict(z_t, t, cond, branches=("uncond",)).eps["uncond"].to(z_t.dtype)
    eps = prior.predict(z_t, t, cond, branches=("cond", "uncond")).eps
    return cfg(eps["uncond"].to(z_t.dtype), eps["cond"].to(z_t.dtype), omega)


@torch.no_grad()
def ddim_sample(
    prior: Prior,
    cond: Condition,
    *,
    steps: int = 50,
    omega: float = 1.0,
    eta: float = 0.0,
    rng: torch.Generator | None = None,
    batch: int | None = None,
    clip_x0: bool = False,
    decode: bool = True,
    z_T: torch.Tensor | None = None,
    dtype: torch.dtype = torch.float32,
) -> DDIMResult:
    """Sample with DDIM (eq. 12 of Song et al. 2021) and classifier-free guidance weight ``omega``.

    ``batch`` defaults to the batch of ``z_T`` or of the condition (its image, or its list of
    labels), else 1.
    ``z_T`` overrides the initial noise (B, C, h, w); otherwise it is drawn from ``rng``,
    as is the step noise when ``eta > 0`` — the same seed gives the same samples.
    ``clip_x0`` clamps x̂₀ to [−1, 1] and recomputes ε̂ from it, as DDPM/DDIM reference code does for
    pixel-space models: the data lie in [−1, 1], and an x̂₀ outside it (large at high t for an
    under-trained ε-model) would otherwise be carried into every later step. Leave it off for latent
    priors, whose latents are not bounded by 1.
    """
    if eta < 0:
        raise ValueError(f"ddim: eta must be >= 0, got {eta}")
    sched = prior.schedule
    ts = ddim_timesteps(sched.num_steps, steps)
    b = _batch_size(cond, batch, z_T)
    dev = _device(prior, cond)
    shape = (b, *prior.sample_shape)
    if z_T is not None:
        if tuple(z_T.shape) != shape:
            raise ValueError(f"ddim: z_T has shape {tuple(z_T.shape)}; expected {shape}")
        z = z_T.to(device=dev, dtype=dtype)
    else:
        z = randn(shape, rng, dev, dtype)
    abar = sched.alphas_cumprod  # float64 (T,)

    for i, t in enumerate(ts):
        s = ts[i + 1] if i + 1 < len(ts) else None
        a_t = float(abar[t])
        a_s = float(abar[s]) if s is not None else 1.0
        t_vec = torch.full((b,), t, dtype=torch.long, device=dev)
        eps = guided_eps(prior, z, t_vec, cond, omega)
        x0 = (z - math.sqrt(1.0 - a_t) * eps) / math.sqrt(a_t)
        if clip_x0:
            x0 = x0.clamp(-1.0, 1.0)
            eps = (z - math.sqrt(a_t) * x0) / math.sqrt(1.0 - a_t)
        sigma = eta * math.sqrt((1.0 - a_s) / (1.0 - a_t)) * math.sqrt(max(0.0, 1.0 - a_t / a_s))
        z = math.sqrt(a_s) * x0 + math.sqrt(max(0.0, 1.0 - a_s - sigma**2)) * eps
        if sigma > 0:
            z = z + sigma * randn(shape, rng, dev, dtype)

    image = prior.decode(z).clamp(0.0, 1.0) if decode else None
    return DDIMResult(z=z, image=image)
