"""``UNetPrior``: a compact conditional pixel-space diffusion UNet (the bundled prior's network).

Architecture (ADM-style, Dhariwal & Nichol 2021, scaled down):

* input: the noisy image z_t (C_img channels, [−1, 1] space) concatenated with the conditioning
  image (ControlNet-style, e.g. the albedo; C_cond channels mapped from [0, 1] to [−1, 1]);
* embedding: sinusoidal(t) → MLP, plus a learned label embedding whose last row is the null label
  (index ``len(vocabulary)``), the unconditional branch of classifier-free guidance (Ho & Salimans
  2022); training drops labels to null with probability ``p_uncond``. With ``directions`` the label is a
  light direction instead (issue #11: any direction, a named light being just its direction): the unit
  vector l (``lasagna.document.condition``: a name or ``az=…,el=…``) → Fourier features [l, sin 2^k π l,
  cos 2^k π l] → MLP, and the null label a learned vector. The network then takes (B, 4) rows (l, null flag);
* encoder: per level ``res_blocks`` residual blocks, then a stride-2 conv; a middle block (with
  self-attention when ``attention=True``); a mirrored decoder with skip connections; a zero-initialised
  output conv, so the untrained network predicts 0 (for v-prediction: x̂₀ = √ᾱ z_t).
* output: ε or v (Salimans & Ho 2022). ``_eps`` always returns ε, converting v through the schedule.
  v-prediction is the default: the CPU prototype measured that ε-prediction under-trained the high-t
  end (x̂₀ reached |x̂₀| ≈ 36 at t = 979) and v-prediction fixed it (../shared/DESIGN.md).

Channels (32, 64, 128) with one residual block per level give ≈1.6 M parameters at 32² (≈2.0 M with attention).
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from torch import nn

from lasagna.errors import ConditionError
from lasagna.io.checkpoint import Pretrained
from lasagna.limits import MAX_GENERATOR_BLOCKS, MAX_GENERATOR_LEVELS, MAX_GENERATOR_WIDTH, MAX_VOCABULARY
from lasagna.priors.base import NoiseSchedule, Prior
from lasagna.priors.nn import Downsample, ResBlock, SelfAttention, Upsample, group_norm, randn, timestep_embedding

FORMAT = "lasagna.unet_prior"


class ScheduleConfig(BaseModel):
    """The noise schedule saved with a prior (see ``NoiseSchedule``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    num_steps: int = Field(1000, ge=2)
    kind: Literal["linear", "scaled_linear", "cosine"] = "linear"
    beta_start: float = Field(1e-4, gt=0.0, lt=1.0)
    beta_end: float = Field(0.02, gt=0.0, lt=1.0)

    def build(self) -> NoiseSchedule:
        return NoiseSchedule(self.num_steps, self.kind, self.beta_start, self.beta_end)


class UNetConfig(BaseModel):
    """Everything that rebuilds a ``UNetPrior`` (saved as config.json beside the weights)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    # The bounds are the layer generator's (lasagna.limits): a config.json is read before its weights, and a
    # hostile one (channels [2**40], res_blocks 10**6) must be one line, not an allocation that fails or hangs.
    image_channels: int = Field(3, ge=1, le=MAX_GENERATOR_WIDTH)
    cond_channels: int = Field(
        0, ge=0, le=MAX_GENERATOR_WIDTH, description="channels of the conditioning image; 0 = none"
    )
    resolution: int = Field(32, ge=1, le=2**15)
    channels: tuple[int, ...] = Field(
        (32, 64, 128), min_length=1, max_length=MAX_GENERATOR_LEVELS, description="feature channels per level"
    )
    res_blocks: int = Field(1, ge=1, le=MAX_GENERATOR_BLOCKS, description="residual blocks per level")
    attention: bool = Field(False, description="self-attention in the middle (lowest-resolution) block")
    norm_groups: int = Field(8, ge=1)
    vocabulary: tuple[str, ...] = Field((), max_length=MAX_VOCABULARY)
    directions: bool = Field(
        False,
        description="condition on a light direction (a named label or 'az=…,el=…', as its unit vector) "
        "instead of a label embedding; vocabulary then lists the names shown to people",
    )
    prediction: Literal["epsilon", "v"] = "v"
    schedule: ScheduleConfig = ScheduleConfig()

    @field_validator("vocabulary")
    @classmethod
    def _vocabulary_unique(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        if any(lab == "" for lab in v):
            raise ValueError("labels must be non-empty (the empty label is the null label)")
        if len(set(v)) != len(v):
            raise ValueError(f"labels must be unique; got {list(v)}")
        return v

    @model_validator(mode="after")
    def _shapes(self) -> UNetConfig:
        if any(c > MAX_GENERATOR_WIDTH for c in self.channels):
            raise ValueError(f"channels must lie in [1, {MAX_GENERATOR_WIDTH}]; got {list(self.channels)}")
        bad = [c for c in self.channels if c < 1 or c % self.norm_groups]
        if bad:
            raise ValueError(
                f"every entry of channels must be a positive multiple of norm_groups={self.norm_groups}; got "
                f"{list(self.channels)}"
            )
        factor = 2 ** (len(self.channels) - 1)
        if self.resolution % factor:
            raise ValueError(f"resolution {self.resolution} must be divisible by 2^(levels-1) = {factor}")
        return self

    @property
    def emb_dim(self) -> int:
        return 4 * self.channels[0]


class _Net(nn.Module):
    """The bare UNet: (x (B, C_img + C_cond, H, W), t (B,), label (B,)) -> (B, C_img, H, W)."""

    def __init__(self, cfg: UNetConfig):
        super().__init__()
        ch, g, e = cfg.channels, cfg.norm_groups, cfg.emb_dim
        self.time_mlp = nn.Sequential(nn.Linear(ch[0], e), nn.SiLU(), nn.Linear(e, e))
        self.directions = cfg.directions
        if cfg.directions:
            self.dir_mlp = nn.Sequential(nn.Linear(DIRECTION_FEATURES, e), nn.SiLU(), nn.Linear(e, e))
            self.null_emb = nn.Parameter(torch.zeros(e))
        else:
            self.label_emb = nn.Embedding(len(cfg.vocabulary) + 1, e)  # last row: the null label
        self.inp = nn.Conv2d(cfg.image_channels + cfg.cond_channels, ch[0], 3, padding=1)
        self.down = nn.ModuleList()
        prev = ch[0]
        for i, c in enumerate(ch):
            blocks = nn.ModuleList(ResBlock(prev if j == 0 else c, c, e, g) for j in range(cfg.res_blocks))
            self.down.append(
                nn.ModuleDict({"blocks": blocks, "down": Downsample(c) if i < len(ch) - 1 else nn.Identity()})
            )
            prev = c
        self.mid1 = ResBlock(ch[-1], ch[-1], e, g)
        self.mid_attn = SelfAttention(ch[-1], g) if cfg.attention else None
        self.mid2 = ResBlock(ch[-1], ch[-1], e, g) if cfg.attention else None
        self.up = nn.ModuleList()
        for i in reversed(range(len(ch))):
            below = ch[i + 1] if i < len(ch) - 1 else ch[-1]  # channels arriving from the level below
            blocks = nn.ModuleList(
                ResBlock(below + ch[i] if j == 0 else ch[i], ch[i], e, g) for j in range(cfg.res_blocks)
            )
            self.up.append(nn.ModuleDict({"blocks": blocks, "up": Upsample(ch[i]) if i > 0 else nn.Identity()}))
        self.out_norm = group_norm(ch[0], g)
        self.out = nn.Conv2d(ch[0], cfg.image_channels, 3, padding=1)
        nn.init.zeros_(self.out.weight)  # the untrained prior predicts 0 (see the module docstring)
        nn.init.zeros_(self.out.bias)
        self._t_dim = ch[0]

    def forward(self, x: torch.Tensor, t: torch.Tensor, label: torch.Tensor) -> torch.Tensor:
        emb = self.time_mlp(timestep_embedding(t, self._t_dim).to(x.dtype)) + self.label_embedding(label, x.dtype)
        h = self.inp(x)
        skips = []
        for level in self.down:
            for blk in level["blocks"]:
                h = blk(h, emb)
            skips.append(h)
            h = level["down"](h)
        h = self.mid1(h, emb)
        if self.mid_attn is not None:
            h = self.mid2(self.mid_attn(h), emb)
        for level in self.up:
            h = torch.cat([h, skips.pop()], dim=1)
            for blk in level["blocks"]:
                h = blk(h, emb)
            h = level["up"](h)
        return self.out(F.silu(self.out_norm(h)))

    def label_embedding(self, label: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """(B, E): the label's embedding; with ``directions``, label rows are (l_x, l_y, l_z, null flag)."""
        if not self.directions:
            return self.label_emb(label)
        feats = direction_features(label[:, :3].to(dtype))
        null = label[:, 3:4].to(dtype) > 0.5
        return torch.where(null, self.null_emb.to(dtype).expand(label.shape[0], -1), self.dir_mlp(feats))


DIRECTION_OCTAVES = 3
"""Fourier octaves of the direction features: sin/cos of 2^k π l, k < 3, resolve the eight named lights (45°
apart) and what lies between them without a lookup table."""
DIRECTION_FEATURES = 3 * (1 + 2 * DIRECTION_OCTAVES)


def direction_features(unit: torch.Tensor) -> torch.Tensor:
    """(B, 3) unit vectors → (B, DIRECTION_FEATURES): [l, sin 2^k π l, cos 2^k π l] for k < DIRECTION_OCTAVES."""
    parts = [unit]
    for k in range(DIRECTION_OCTAVES):
        parts += [torch.sin((2**k) * torch.pi * unit), torch.cos((2**k) * torch.pi * unit)]
    return torch.cat(parts, dim=1)


def direction_rows(labels, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """(B, 4) rows (l, null flag) of condition texts: a named light or ``az=…,el=…``; None or "" is null."""
    from lasagna.document.condition import parse_direction, unit_vector

    rows = []
    for lab in labels:
        if lab is None or lab == "":
            rows.append((0.0, 0.0, 0.0, 1.0))
        else:
            rows.append((*unit_vector(*parse_direction(lab)), 0.0))
    return torch.tensor(rows, dtype=dtype)


class UNetPrior(Pretrained, Prior):
    """A conditional pixel-space diffusion prior (see the module docstring)."""

    FORMAT = FORMAT
    CONFIG = UNetConfig

    def __init__(self, config: UNetConfig):
        super().__init__()
        self.config = config
        self.schedule = config.schedule.build()
        self.vocabulary = tuple(config.vocabulary)
        self.sample_shape = (config.image_channels, config.resolution, config.resolution)
        self.net = _Net(config)

    def label_tensor(self, labels) -> torch.Tensor:
        if not self.config.directions:
            return self.label_index(labels)
        try:
            return direction_rows(labels)
        except ConditionError as exc:
            raise ConditionError(exc.message, "condition.labels") from None

    def null_tensor(self, batch: int) -> torch.Tensor:
        if not self.config.directions:
            return super().null_tensor(batch)
        return direction_rows([None] * batch)

    # -- the raw network ------------------------------------------------------------------------
    def _inputs(self, z_t: torch.Tensor, image: torch.Tensor | None) -> torch.Tensor:
        cfg = self.config
        if z_t.dim() != 4 or tuple(z_t.shape[1:]) != self.sample_shape:
            raise ConditionError(
                f"z_t has shape {tuple(z_t.shape)}; expected (B, {', '.join(map(str, self.sample_shape))})", "z_t"
            )
        if cfg.cond_channels == 0:
            if image is not None:
                raise ConditionError(
                    "this prior takes no conditioning image (cond_channels = 0); expected image=None", "condition.image"
                )
            return z_t
        expected = f"(B, {cfg.cond_channels}, {cfg.resolution}, {cfg.resolution})"
        if image is None:
            raise ConditionError(
                f"this prior needs a conditioning image of shape {expected}; got None", "condition.image"
            )
        if image.dim() != 4 or tuple(image.shape[1:]) != (cfg.cond_channels, cfg.resolution, cfg.resolution):
            raise ConditionError(f"image has shape {tuple(image.shape)}; expected {expected}", "condition.image")
        if image.shape[0] != z_t.shape[0]:
            raise ConditionError(
                f"image has batch {image.shape[0]}; expected the batch of z_t, {z_t.shape[0]}", "condition.image"
            )
        # The conditioning image arrives in [0, 1] (Condition's convention); the network sees it in
        # the same [−1, 1] range as z.
        return torch.cat([z_t, image.to(z_t.dtype) * 2 - 1], dim=1)

    def raw(
        self, z_t: torch.Tensor, t: torch.Tensor, label_idx: torch.Tensor, image: torch.Tensor | None
    ) -> torch.Tensor:
        """The network's own output (ε or v, per ``config.prediction``), in the parameters' dtype."""
        dtype = self.net.inp.weight.dtype
        z_t = z_t.to(dtype)
        x = self._inputs(z_t, image)
        if self.net.inp.weight.is_contiguous(memory_format=torch.channels_last):  # `channels_last`: NHWC through
            x = x.contiguous(memory_format=torch.channels_last)
            return self.net(x, t.to(z_t.device), label_idx.to(z_t.device)).contiguous()
        return self.net(x, t.to(z_t.device), label_idx.to(z_t.device))

    def channels_last(self) -> UNetPrior:
        """Lay the network's weights out NHWC, and so its activations in `raw`: a frozen prior on the CPU, where
        oneDNN's convolutions run this UNet's 32² batches ~15–20 % faster that way (``benchmarks/prior_pass.py``),
        the same values to float32 rounding. Returns the prior."""
        self.net.to(memory_format=torch.channels_last)
        return self

    def _eps(
        self, z_t: torch.Tensor, t: torch.Tensor, label_idx: torch.Tensor, image: torch.Tensor | None
    ) -> torch.Tensor:
        out = self.raw(z_t, t, label_idx, image)
        if self.config.prediction == "v":
            return self.schedule.eps_from_v(z_t.to(out.dtype), out, t)
        return out

    # -- training objective (reused by the training issue) --------------------------------------
    def training_loss(
        self,
        x0: torch.Tensor,
        labels_idx: torch.Tensor,
        image: torch.Tensor | None,
        rng: torch.Generator | None = None,
        p_uncond: float = 0.15,
    ) -> torch.Tensor:
        """The simple diffusion objective (Ho et al. 2020, eq. 14) for this prior's prediction type.

        ``x0``: clean images in the denoiser space ([−1, 1]), (B, C, H, W). ``labels_idx``: (B,)
        vocabulary indices (the null index allowed). Labels are replaced by the null label with
        probability ``p_uncond`` (classifier-free guidance training); the conditioning image is kept,
        matching how the unconditional branch is queried. t ~ U{0, …, T − 1}; the target is ε or
        v = √ᾱ ε − √(1 − ᾱ) x₀ (Salimans & Ho 2022). Returns the mean squared error.
        """
        if not 0.0 <= p_uncond <= 1.0:
            raise ValueError(f"p_uncond must be in [0, 1], got {p_uncond}")
        b, dev = x0.shape[0], x0.device
        t = torch.randint(0, self.schedule.num_steps, (b,), generator=rng, device=_rng_device(rng, dev)).to(dev)
        eps = randn(tuple(x0.shape), rng, dev, x0.dtype)
        drop = torch.rand((b,), generator=rng, device=_rng_device(rng, dev)).to(dev) < p_uncond
        if self.config.directions:  # labels_idx are (B, 4) direction rows; a dropped one becomes the null row
            null = self.null_tensor(b).to(dev, labels_idx.dtype)
            labels = torch.where(drop[:, None], null, labels_idx.to(dev))
        else:
            labels = torch.where(drop, torch.full_like(labels_idx.to(dev), len(self.vocabulary)), labels_idx.to(dev))
        z_t = self.schedule.add_noise(x0, eps, t)
        if self.config.prediction == "v":
            ab = self.schedule.alpha_bar(t, x0.dtype)[:, None, None, None]
            target = ab.sqrt() * eps - (1 - ab).sqrt() * x0
        else:
            target = eps
        out = self.raw(z_t, t, labels, image)
        return F.mse_loss(out.float(), target.float())


def _rng_device(rng: torch.Generator | None, fallback: torch.device) -> torch.device:
    return rng.device if rng is not None else fallback
