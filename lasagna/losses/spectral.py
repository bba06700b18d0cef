"""A spectral manifold corrective: b̂ as a per-timestep linear frequency response, fitted in closed form.

LMC-SDS (Alldieck et al., Sec. 4) motivates b̂ as the denoiser's *timestep-dependent frequency bias*:
on a clean image z the prior's estimate ẑ_t is z with some frequencies attenuated, and L_lmc = b̂ − ẑ_t
(eq. 9) removes that bias from the gradient, keeping only the pull towards the manifold. This module
models exactly that bias and nothing else: for each timestep bucket k and channel c,

    b̂(z, t) = F⁻¹[ H_k(c, f) · F[z](c, f) ]        (k = bucket of t, F = 2-D real FFT)

a linear, shift-invariant filter per t (periodic boundary). Fitted by least squares on triplets
(z, ẑ_t, t) of clean world images (``lasagna.training.corrective.make_triplets``' recipe, unconditional branch),
per frequency: H_k(c, f) = Σ Ẑ_t(c, f) · conj Z(c, f) / Σ |Z(c, f)|² — the Wiener estimate of the
denoiser's response, exact for the mean-square fit of a linear filter, no iterations.

Why a filter and not the paper's network: a corrective that can see the condition (or, with enough
capacity, infer the scene from z) learns E[ẑ_t | z] itself, and then L_lmc = b̂ − ẑ_t cancels the
manifold pull too — an exact b̂ makes E[L_lmc] vanish everywhere, on the manifold or not
(``lmc_sds`` docstring, point 3). The network b̂ shipped as ``relight-32-bhat`` (L_k 0.19× that of
b̂ = z) made LMC-SDS *worse* than SDS at every ω; a linear filter cannot hallucinate shading, so
what it removes is the frequency bias only (docs/BENCHMARKS.md#learned-layers).

Stored like the other networks (``lasagna.io.checkpoint.Pretrained``): config.json (format
``lasagna.spectral_corrective``) and model.safetensors with the gains' real and imaginary parts
(safetensors has no complex dtype).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from lasagna.io.checkpoint import Pretrained
from lasagna.numerics import SPECTRAL_POWER_FLOOR

FORMAT = "lasagna.spectral_corrective"


class SpectralCorrectiveConfig(BaseModel):
    """What rebuilds a ``SpectralCorrective`` (its fitted gains are the weights)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    channels: int = Field(3, ge=1, description="channels of z (the prior's space)")
    height: int = Field(32, ge=1)
    width: int = Field(32, ge=1)
    buckets: int = Field(50, ge=1, description="timestep buckets of equal width over [0, num_timesteps)")
    num_timesteps: int = Field(1000, ge=2, description="T of the prior's schedule")
    fit_images: int = Field(0, ge=0, description="clean images per bucket the gains were fitted on (a record)")


class SpectralCorrective(Pretrained, nn.Module):
    """b̂(z, t) = irfft2(H[bucket(t)] · rfft2(z)) — see the module docstring. Any z of the fitted size."""

    FORMAT = FORMAT
    CONFIG = SpectralCorrectiveConfig

    def __init__(self, config: SpectralCorrectiveConfig):
        super().__init__()
        self.config = config
        shape = (config.buckets, config.channels, config.height, config.width // 2 + 1)
        self.register_buffer("gain_real", torch.ones(shape))  # identity until fitted
        self.register_buffer("gain_imag", torch.zeros(shape))

    def bucket(self, t: torch.Tensor) -> torch.Tensor:
        """(B,) integer timesteps → (B,) bucket indices."""
        k = (t.long() * self.config.buckets) // self.config.num_timesteps
        return k.clamp(0, self.config.buckets - 1)

    def forward(
        self,
        z: torch.Tensor,
        t: torch.Tensor,
        cond_image: torch.Tensor | None = None,
        label_idx: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """b̂ for z (B, C, H, W) at integer timesteps t (B,); the condition is ignored by design."""
        c = self.config
        if z.dim() != 4 or tuple(z.shape[1:]) != (c.channels, c.height, c.width):
            raise ValueError(
                f"spectral corrective: z has shape {tuple(z.shape)}; expected (B, {c.channels}, {c.height}, {c.width})"
            )
        k = self.bucket(t.to(self.gain_real.device))
        gain = torch.complex(self.gain_real[k], self.gain_imag[k])  # (B, C, H, W//2+1)
        spec = torch.fft.rfft2(z.float())
        return torch.fft.irfft2(gain * spec, s=(c.height, c.width)).to(z.dtype)


@torch.no_grad()
def fit_spectral_corrective(
    config: SpectralCorrectiveConfig,
    draw: Callable[[int], tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
    batches: int,
) -> SpectralCorrective:
    """Least-squares gains from ``batches`` calls of ``draw(bucket) -> (z, t, ẑ_t)`` per bucket.

    ``draw`` returns clean z (B, C, H, W), their timesteps t (B,) inside the bucket, and the prior's
    estimates ẑ_t; sums are accumulated in float64 (complex128) so the fit does not depend on the
    order or number of batches beyond rounding.
    """
    model = SpectralCorrective(config)
    fh = config.width // 2 + 1
    num = torch.zeros(config.buckets, config.channels, config.height, fh, dtype=torch.complex128)
    den = torch.zeros(config.buckets, config.channels, config.height, fh, dtype=torch.float64)
    count = 0
    for k in range(config.buckets):
        for _ in range(batches):
            z, t, z_hat = draw(k)
            if bool((model.bucket(t) != k).any()):
                raise ValueError(f"draw({k}) returned timesteps outside bucket {k}: {t.tolist()}")
            zf, hf = torch.fft.rfft2(z.double()), torch.fft.rfft2(z_hat.double())
            num[k] += (hf * zf.conj()).sum(0)
            den[k] += (zf.abs() ** 2).sum(0)
            if k == 0:
                count += z.shape[0]
    fitted = den > SPECTRAL_POWER_FLOOR  # unexcited frequencies keep the identity gain (numerics)
    gain = torch.where(fitted, num / den.clamp_min(SPECTRAL_POWER_FLOOR), torch.ones_like(num))
    model.gain_real.copy_(gain.real.float())
    model.gain_imag.copy_(gain.imag.float())
    model.config = config.model_copy(update={"fit_images": count})
    return model.eval()
