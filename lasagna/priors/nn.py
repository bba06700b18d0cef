"""Building blocks shared by the pixel UNet prior and the manifold corrective.

* ``timestep_embedding``: the sinusoidal embedding of Vaswani et al. (2017) as used for diffusion
  timesteps by Ho et al. (2020) and ADM (Dhariwal & Nichol 2021).
* ``frequency_encoding``: the NeRF-style encoding [sin(2^k π x), cos(2^k π x)], k < K, that the
  LMC-SDS paper uses to feed t (and class ids) to its U-Nets (supplementary: "10-dimensional
  frequency encoding" = K = 5 frequencies).
* ``ResBlock``, ``SelfAttention``, ``Downsample``, ``Upsample``: the ADM-style blocks of the prior.
* ``randn``: seeded Gaussian noise from a ``torch.Generator`` on any device.

Everything here is a plain function or a small ``nn.Module`` with shape comments; no block reads
configuration of its own.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10_000.0) -> torch.Tensor:
    """Sinusoidal embedding (B,) -> (B, dim): [cos(t·f_i), sin(t·f_i)], f_i = max_period^(−i/(dim/2)).

    ``t`` is the integer timestep (as ADM feeds it), converted to float32 so the phase of large t
    is exact enough; the caller casts the result to the network's dtype.
    """
    if dim % 2:
        raise ValueError(f"timestep_embedding: dim must be even, got {dim}")
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    args = t.to(torch.float32)[:, None] * freqs[None]  # (B, half)
    return torch.cat([torch.cos(args), torch.sin(args)], dim=1)


def frequency_encoding(x: torch.Tensor, num_freqs: int = 5) -> torch.Tensor:
    """NeRF-style encoding (B,) -> (B, 2·num_freqs): [sin(2^k π x) for k] + [cos(2^k π x) for k].

    Meant for x ∈ [0, 1] (t / (T − 1), or a class id scaled to [0, 1]); the LMC-SDS supplementary
    encodes t with 10 dimensions, i.e. ``num_freqs=5``.
    """
    if num_freqs < 1:
        raise ValueError(f"frequency_encoding: num_freqs must be >= 1, got {num_freqs}")
    scales = (2.0 ** torch.arange(num_freqs, dtype=torch.float32, device=x.device)) * math.pi  # (K,)
    args = x.to(torch.float32)[:, None] * scales[None]  # (B, K)
    return torch.cat([torch.sin(args), torch.cos(args)], dim=1)


def group_norm(channels: int, groups: int) -> nn.GroupNorm:
    """GroupNorm that refuses a group count that does not divide the channels (no silent fallback)."""
    if channels % groups:
        raise ValueError(f"group_norm: {channels} channels are not divisible by {groups} groups")
    return nn.GroupNorm(groups, channels)


def randn(shape: tuple[int, ...], rng: torch.Generator | None, device, dtype: torch.dtype) -> torch.Tensor:
    """N(0, I) noise drawn on the rng's device (so a CPU rng seeds GPU runs too)."""
    rng_device = rng.device if rng is not None else device
    return torch.randn(shape, generator=rng, device=rng_device, dtype=dtype).to(device)


class ResBlock(nn.Module):
    """GN-SiLU-Conv, + embedding, GN-SiLU-Conv, + skip (ADM's residual block without scale-shift)."""

    def __init__(self, in_ch: int, out_ch: int, emb_dim: int, groups: int):
        super().__init__()
        self.norm1 = group_norm(in_ch, groups)
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, padding=1)
        self.emb = nn.Linear(emb_dim, out_ch)
        self.norm2 = group_norm(out_ch, groups)
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, padding=1)
        # Zero-initialised last conv: each block starts as the identity, which keeps the variance of
        # a deep stack of residual blocks at one at initialisation (Goyal et al. 2017; ADM does so).
        nn.init.zeros_(self.conv2.weight)
        nn.init.zeros_(self.conv2.bias)
        self.skip = nn.Identity() if in_ch == out_ch else nn.Conv2d(in_ch, out_ch, 1)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x)))  # (B, out, H, W)
        h = h + self.emb(F.silu(emb))[:, :, None, None]
        h = self.conv2(F.silu(self.norm2(h)))
        return self.skip(x) + h


class SelfAttention(nn.Module):
    """Single-head spatial self-attention with a residual connection (used at the lowest level)."""

    def __init__(self, channels: int, groups: int):
        super().__init__()
        self.norm = group_norm(channels, groups)
        self.qkv = nn.Conv2d(channels, 3 * channels, 1)
        self.proj = nn.Conv2d(channels, channels, 1)
        nn.init.zeros_(self.proj.weight)
        nn.init.zeros_(self.proj.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        q, k, v = self.qkv(self.norm(x)).reshape(b, 3, c, h * w).unbind(1)  # each (B, C, HW)
        out = F.scaled_dot_product_attention(q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2))  # (B, HW, C)
        return x + self.proj(out.transpose(1, 2).reshape(b, c, h, w))


class Downsample(nn.Module):
    """Stride-2 3×3 convolution: (B, C, H, W) -> (B, C, H/2, W/2)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, stride=2, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(x)


class Upsample(nn.Module):
    """Nearest-neighbour ×2 then a 3×3 convolution (avoids transposed-conv checkerboards)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.interpolate(x, scale_factor=2.0, mode="nearest"))
