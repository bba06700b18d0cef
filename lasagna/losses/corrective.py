"""The learned manifold corrective b̂_ψ of LMC-SDS (Alldieck et al., Sec. 4, eq. 8–10) and its loss L_k.

The denoiser's clean-image estimate ẑ_t = z_φ(z_t, t) is modelled as b(p(z_t, t), t) (eq. 8): a
projection p onto the image manifold followed by a t-dependent frequency bias b ("blur"). b̂_ψ(z, t)
learns b from triplets (z, ẑ_t, t) so that L_lmc = b̂(z, t) − ẑ_t (eq. 9) keeps only the manifold
part of the SDS gradient.

**L_k (eq. 10).** b̂'s output is rescaled to the standard deviation of the target about its OWN
mean, then compared with the target:

    b̃ = σ(ẑ_t)/σ(b̂) · (b̂ − μ(b̂)) + μ(b̂),        L_k = ‖ẑ_t − b̃‖²

so b̂ cannot lower the loss by shrinking image dynamics (the paper saw a b̂ trained with plain L2
underestimate contrast at large t, which made LMC-SDS over-saturate). Only σ is taken from the target;
the mean stays b̂'s. μ and σ are per sample over all of (C, H, W) (the "global image statistics"); σ is
the population standard deviation, guarded by ``lasagna.numerics.STD_EPS`` so a constant b̂ (σ = 0)
gives a finite loss and a finite gradient. ‖·‖² is averaged over elements (a per-pixel MSE), so
values compare across resolutions. ``rescale_to_target_std(b̂, ẑ_t)`` is the normalisation LMC-SDS
applies to b̂ in eq. 9 (``lmc_sds.normalize_like`` calls ``rescale_to_target_std``).

**The network.** The paper's b̂ is a plain U-Net: per encoder level two Conv/ReLU blocks then a
MaxPool, 32 filters doubling per level, skip connections, a final conv with tanh; t enters as a
10-dim frequency encoding concatenated to every pixel. We read "two Conv/ReLU/MaxPool blocks per
layer" as two Conv3×3+ReLU followed by one 2×2 max-pool. Here ``filters`` lists the levels, the
last being the bottleneck (no pool after it); the decoder mirrors the others (nearest ×2, concat the
skip, two Conv+ReLU). The paper's "four encoder layers … nine layers" is ``filters`` of length 5
(32…512); at our resolutions 3–4 levels suffice (32²: (32, 64, 128); 64²: (32, 64, 128, 256)).
The output is **residual**:

    b̂(z, t) = z + scale · tanh(net(z, enc(t), …))      with the last conv zero-initialised,

so the untrained b̂ is exactly the trivial corrective b̂ = z: σ(b̂) = σ(z) > 0 for any non-constant z
(a directly predicted b̂ starts near a constant, where the normalisation of eq. 10 divides by ≈ 0),
training starts from the baseline it must beat, and b̂ only has to learn the bias, not to copy z.
``scale`` = 2 lets the correction span the whole [−1, 1] pixel range.

``sees_condition`` (an option; not in the paper): b̂ also sees the conditioning image and the
sample's label (a learned embedding per pixel). The CPU prototype's corrective saw only (z, t) and
leaked albedo texture into shading layers; ẑ_t of a ControlNet-style prior depends on the
conditioning image, which a (z, t)-only b̂ cannot know (../shared/DESIGN.md).
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from torch import nn

from lasagna.errors import ConditionError
from lasagna.io.checkpoint import Pretrained
from lasagna.numerics import STD_EPS, reduction_dtype
from lasagna.priors.nn import frequency_encoding

FORMAT = "lasagna.corrective"


# ---------------------------------------------------------------------------------------------
# L_k (eq. 10)
# ---------------------------------------------------------------------------------------------
def mean_std(x: torch.Tensor, eps: float = STD_EPS) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample mean and population std over all non-batch dims, shaped (B, 1, …, 1).

    σ = √max(var, eps²): clamping the variance (not σ) keeps the gradient finite at var = 0, where
    d√v/dv is infinite; computed in float32 for half-precision inputs.
    """
    dims = tuple(range(1, x.dim()))
    xr = x.to(reduction_dtype(x.dtype))
    mu = xr.mean(dim=dims, keepdim=True)
    var = ((xr - mu) ** 2).mean(dim=dims, keepdim=True)
    return mu, var.clamp_min(eps * eps).sqrt()


def normalize_by_std(x: torch.Tensor, eps: float = STD_EPS) -> torch.Tensor:
    """(x − μ(x)) / σ(x) per sample, σ guarded by ``eps`` (a constant image maps to 0)."""
    mu, sigma = mean_std(x, eps)
    return ((x - mu) / sigma).to(x.dtype)


def rescale_to_target_std(b_hat: torch.Tensor, target: torch.Tensor, eps: float = STD_EPS) -> torch.Tensor:
    """b̃ = σ(target)/σ(b̂) · (b̂ − μ(b̂)) + μ(b̂): eq. 10's normalisation (b̂ keeps its mean, takes the target's σ)."""
    if b_hat.shape != target.shape:
        raise ValueError(
            f"rescale_to_target_std: b_hat has shape {tuple(b_hat.shape)}, target {tuple(target.shape)}; expected "
            "equal shapes"
        )
    return _rescale(b_hat, target, eps).to(b_hat.dtype)


def _rescale(b_hat: torch.Tensor, target: torch.Tensor, eps: float) -> torch.Tensor:
    """``rescale_to_target_std`` left in the reduction dtype (float32 for half inputs)."""
    mu_b, sigma_b = mean_std(b_hat, eps)
    _, sigma_t = mean_std(target, eps)
    return sigma_t / sigma_b * (b_hat.to(mu_b.dtype) - mu_b) + mu_b


def lk_loss(
    b_hat: torch.Tensor, z_hat_t: torch.Tensor, reduction: Literal["mean", "none"] = "mean", eps: float = STD_EPS
) -> torch.Tensor:
    """L_k (eq. 10): mean over elements of (ẑ_t − b̃)², b̃ = ``rescale_to_target_std(b̂, ẑ_t)``.

    ``reduction="none"`` returns one value per sample (B,); "mean" averages them. The target ẑ_t is
    treated as data (no gradient is needed through it, but none is blocked either). Computed in
    float32 for half-precision inputs. Near σ(b̂) = 0 the gradient scales like σ(ẑ)/STD_EPS: finite
    in float32/bfloat16, but it can overflow float16 (the residual b̂ = z + … keeps σ(b̂) away from 0).
    """
    if b_hat.shape != z_hat_t.shape:
        raise ValueError(
            f"lk_loss: b_hat has shape {tuple(b_hat.shape)}, z_hat_t {tuple(z_hat_t.shape)}; expected equal shapes"
        )
    b_tilde = _rescale(b_hat, z_hat_t, eps)
    diff = z_hat_t.to(b_tilde.dtype) - b_tilde
    per_sample = (diff**2).flatten(1).mean(dim=1)
    if reduction == "none":
        return per_sample
    if reduction == "mean":
        return per_sample.mean()
    raise ValueError(f"lk_loss: reduction must be 'mean' or 'none', got {reduction!r}")


corrective_loss = lk_loss  # the name issue #3 uses for L_k


# ---------------------------------------------------------------------------------------------
# b̂_ψ
# ---------------------------------------------------------------------------------------------
class CorrectiveConfig(BaseModel):
    """Everything that rebuilds a ``Corrective`` (saved as config.json beside the weights)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    channels: int = Field(3, ge=1, description="channels of z (the prior's space)")
    resolution: int = Field(32, ge=1, description="the resolution trained at (any multiple of 2^(levels-1) runs)")
    filters: tuple[int, ...] = Field(
        (32, 64, 128), min_length=1, description="filters per encoder level (paper: 32 doubling)"
    )
    num_freqs: int = Field(5, ge=1, description="frequencies of the t encoding (2·num_freqs dims; paper: 10 dims)")
    num_timesteps: int = Field(1000, ge=2, description="T of the prior's schedule; t is encoded as t/(T−1)")
    output_scale: float = Field(2.0, gt=0.0, description="b̂ = z + output_scale·tanh(net)")
    sees_condition: bool = False
    cond_channels: int = Field(0, ge=0, description="channels of the conditioning image (when sees_condition)")
    vocabulary: tuple[str, ...] = ()
    label_dim: int = Field(8, ge=1, description="label embedding size (when sees_condition)")

    @field_validator("vocabulary")
    @classmethod
    def _unique(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        if len(set(v)) != len(v) or "" in v:
            raise ValueError(f"labels must be unique and non-empty; got {list(v)}")
        return v

    @model_validator(mode="after")
    def _check(self) -> CorrectiveConfig:
        if any(f < 1 for f in self.filters):
            raise ValueError(f"filters must be positive; got {list(self.filters)}")
        factor = 2 ** (len(self.filters) - 1)
        if self.resolution % factor:
            raise ValueError(f"resolution {self.resolution} must be divisible by 2^(levels-1) = {factor}")
        return self


def _conv_block(in_ch: int, out_ch: int) -> nn.Sequential:
    """Two Conv3×3/ReLU blocks (the paper's per-level unit; the MaxPool follows in the encoder)."""
    return nn.Sequential(
        nn.Conv2d(in_ch, out_ch, 3, padding=1), nn.ReLU(), nn.Conv2d(out_ch, out_ch, 3, padding=1), nn.ReLU()
    )


class Corrective(Pretrained, nn.Module):
    """b̂_ψ(z, t[, image, label]) = z + scale·tanh(UNet(…)) (see the module docstring)."""

    FORMAT = FORMAT
    CONFIG = CorrectiveConfig

    def __init__(self, config: CorrectiveConfig):
        super().__init__()
        self.config = config
        f = config.filters
        extra = 2 * config.num_freqs
        if config.sees_condition:
            extra += config.cond_channels + config.label_dim
            self.label_emb = nn.Embedding(len(config.vocabulary) + 1, config.label_dim)  # last row: null label
        else:
            self.label_emb = None
        self.enc = nn.ModuleList()
        prev = config.channels + extra
        for c in f:
            self.enc.append(_conv_block(prev, c))
            prev = c
        self.dec = nn.ModuleList(_conv_block(f[i + 1] + f[i], f[i]) for i in reversed(range(len(f) - 1)))
        self.head = nn.Conv2d(f[0], config.channels, 1)
        nn.init.zeros_(self.head.weight)  # b̂ = z at initialisation
        nn.init.zeros_(self.head.bias)

    def _features(
        self, z: torch.Tensor, t: torch.Tensor, image: torch.Tensor | None, label_idx: torch.Tensor | None
    ) -> torch.Tensor:
        cfg = self.config
        b, _, h, w = z.shape
        tt = t.to(z.device).to(torch.float32) / (cfg.num_timesteps - 1)
        parts = [z, frequency_encoding(tt, cfg.num_freqs).to(z.dtype)[:, :, None, None].expand(b, -1, h, w)]
        if cfg.sees_condition:
            if image is None or image.shape[0] != b or image.shape[1] != cfg.cond_channels:
                got = None if image is None else tuple(image.shape)
                raise ConditionError(
                    f"this corrective sees the condition and needs an image (B={b}, C={cfg.cond_channels}, H, W); "
                    f"got {got}",
                    "image",
                )
            if image.shape[-2:] != (h, w):
                # Latent priors: the image is at pixel resolution, z at latent resolution.
                image = F.interpolate(image, size=(h, w), mode="area")
            if label_idx is None or label_idx.shape != (b,):
                got = None if label_idx is None else tuple(label_idx.shape)
                raise ConditionError(
                    f"this corrective sees the condition and needs label_idx of shape ({b},); got {got}", "label_idx"
                )
            lab = self.label_emb(label_idx.to(z.device)).to(z.dtype)  # (B, D)
            parts += [image.to(z.dtype) * 2 - 1, lab[:, :, None, None].expand(b, -1, h, w)]
        return torch.cat(parts, dim=1)

    def forward(
        self,
        z: torch.Tensor,
        t: torch.Tensor,
        cond_image: torch.Tensor | None = None,
        label_idx: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """b̂(z, t) for z (B, C, H, W) in the prior's space and integer timesteps t (B,).

        The signature is the corrective protocol ``lmc_sds.py`` calls: ``b̂(z, t, cond_image=,
        label_idx=)``. With ``sees_condition``: ``cond_image`` (B, C_cond, H', W') in [0, 1] (resized
        to H×W by area averaging if it differs) and ``label_idx`` (B,), the sample's label (the null
        index allowed) — both required. Without ``sees_condition`` both are ignored: such a b̂ is by
        construction a function of (z, t) only.
        """
        cfg = self.config
        if z.dim() != 4 or z.shape[1] != cfg.channels:
            raise ConditionError(f"z has shape {tuple(z.shape)}; expected (B, {cfg.channels}, H, W)", "z")
        factor = 2 ** (len(cfg.filters) - 1)
        if z.shape[2] % factor or z.shape[3] % factor:
            raise ConditionError(f"z is {z.shape[2]}×{z.shape[3]}; expected sides divisible by {factor}", "z")
        h = self._features(z, t, cond_image, label_idx)
        skips = []
        for i, block in enumerate(self.enc):
            h = block(h)
            if i < len(self.enc) - 1:
                skips.append(h)
                h = F.max_pool2d(h, 2)
        for block in self.dec:
            h = F.interpolate(h, scale_factor=2.0, mode="nearest")
            h = block(torch.cat([h, skips.pop()], dim=1))
        return z + cfg.output_scale * torch.tanh(self.head(h))


class TrivialCorrective(nn.Module):
    """b̂(z, t) = z: no correction (L_lmc then equals z − ẑ_t, the SDS projection term without its
    √ᾱ/√(1−ᾱ) weight, eq. 7). The baseline a trained corrective is measured against."""

    def forward(
        self,
        z: torch.Tensor,
        t: torch.Tensor,
        cond_image: torch.Tensor | None = None,
        label_idx: torch.Tensor | None = None,
    ) -> torch.Tensor:
        return z
