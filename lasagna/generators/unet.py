"""``LayerGenerator``: the conditioned convolutional U-Net that turns a base layer into an edit layer.

The Lasagna paper's generator G(θ) = y (a "convolutional UNet", Ronneberger et al. 2015) sees the
base layer x; the LMC-SDS paper's image-to-image network (supplementary, "Image-to-image translation
network") is a U-Net with two Conv blocks per level and skip connections, whose class id is "a float
value encoded using 10-dimensional frequency encoding concatenated to each pixel". Here:

* input: the base (B, 3, H, W) in [0, 1], mapped to [−1, 1], concatenated per pixel with the
  condition — ``condition="frequency"``: label i of V as the float x = (i + ½)/V (the centre of its
  bin: x = 0 and x = 1 would share every encoding except cos(πx)) encoded as [sin(2^k π x),
  cos(2^k π x)], k < ``num_freqs`` (LMC-SDS; 5 frequencies = 10 dims; cos(πx) alone is injective), or
  ``"embedding"``: a learned ``label_dim``-vector per label (the CPU prototype's choice);
* encoder: per level ``blocks`` × (Conv3×3 → SiLU), then 2×2 average pooling (every input pixel gets
  a gradient, so a layer varies smoothly); the last level is the bottleneck; decoder: nearest ×2,
  concatenate the skip, ``blocks`` × (Conv3×3 → SiLU). No normalisation layer: GroupNorm statistics
  depend on the whole image, and the generator must give the same pixel whether it sees a patch or
  the whole image (the patch strategy) — with plain convolutions it is local and fully convolutional;
* head: a 1×1 convolution with **zero weights and the identity pre-activation as bias**, then the
  layer's squash (``layer.activate``): the untrained generator outputs the identity edit for every
  input, so its first composite equals the input (``layer.py`` states the exact values).

Any H, W works: sides that are not multiples of 2^(levels − 1) are padded (replicating the border)
and the output is cropped back. Widths (16, 32, 64, 128) with two blocks per level: ≈ 0.53 M
parameters, a cheap 32² forward.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field, field_validator
from torch import Tensor, nn

from lasagna.errors import ConditionError, LasagnaError
from lasagna.generators.layer import LayerSpec, activate
from lasagna.io.checkpoint import Pretrained
from lasagna.limits import MAX_GENERATOR_BLOCKS, MAX_GENERATOR_LEVELS, MAX_GENERATOR_WIDTH, MAX_VOCABULARY
from lasagna.priors.nn import frequency_encoding

FORMAT = "lasagna.layer_generator"


class LayerGeneratorConfig(BaseModel):
    """Everything that rebuilds a ``LayerGenerator`` (saved as config.json beside the weights)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    layer: LayerSpec = Field(description="The edit layer it produces (blend, channels, range, squash).")
    # The bounds (lasagna.limits) keep a hostile config.json from asking for gigabytes of weights.
    vocabulary: tuple[str, ...] = Field(
        min_length=1, max_length=MAX_VOCABULARY, description="Condition labels, in index order."
    )
    channels: tuple[int, ...] = Field(
        (16, 32, 64, 128),
        min_length=1,
        max_length=MAX_GENERATOR_LEVELS,
        description="Feature widths per level; the last is the bottleneck.",
    )
    blocks: int = Field(2, ge=1, le=MAX_GENERATOR_BLOCKS, description="Conv3×3+SiLU blocks per level.")
    condition: Literal["frequency", "embedding"] = Field("frequency", description="How the label enters each pixel.")
    num_freqs: int = Field(
        5, ge=1, le=32, description="Frequencies of the label's frequency encoding (2·num_freqs dims)."
    )
    label_dim: int = Field(
        8, ge=1, le=MAX_GENERATOR_WIDTH, description="Size of the learned label embedding (condition='embedding')."
    )
    base_channels: int = Field(3, ge=1, le=4, description="Channels of the base layer it reads.")

    @field_validator("vocabulary")
    @classmethod
    def _labels(cls, v: tuple[str, ...]) -> tuple[str, ...]:
        if len(set(v)) != len(v) or any(not lab for lab in v):
            raise ValueError(f"labels must be unique and non-empty; got {list(v)}")
        return v

    @field_validator("channels")
    @classmethod
    def _widths(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        if any(c < 1 or c > MAX_GENERATOR_WIDTH for c in v):
            raise ValueError(f"widths must lie in [1, {MAX_GENERATOR_WIDTH}]; got {list(v)}")
        return v

    @classmethod
    def for_preset(cls, preset, **overrides) -> LayerGeneratorConfig:
        """A config producing ``preset``'s layer, conditioned on its vocabulary."""
        return cls(layer=LayerSpec.from_preset(preset), vocabulary=tuple(preset.vocabulary), **overrides)

    @property
    def condition_dim(self) -> int:
        return 2 * self.num_freqs if self.condition == "frequency" else self.label_dim


def _convs(in_ch: int, out_ch: int, blocks: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(blocks):
        layers += [nn.Conv2d(in_ch if i == 0 else out_ch, out_ch, 3, padding=1), nn.SiLU()]
    return nn.Sequential(*layers)


def unet_body(in_channels: int, channels: Sequence[int], blocks: int) -> tuple[nn.ModuleList, nn.ModuleList]:
    """The encoder and decoder of the module docstring's U-Net: per level ``blocks`` × (Conv3×3 → SiLU), the last
    level the bottleneck; a decoder level per skip (the layer generator's and the surface estimator's)."""
    enc, prev = nn.ModuleList(), in_channels
    for c in channels:
        enc.append(_convs(prev, c, blocks))
        prev = c
    ch = channels
    dec = nn.ModuleList(_convs(ch[i + 1] + ch[i], ch[i], blocks) for i in reversed(range(len(ch) - 1)))
    return enc, dec


def run_unet(enc: nn.ModuleList, dec: nn.ModuleList, x: Tensor) -> Tensor:
    """The U-Net's features at the input's size: encode with 2×2 average pooling between levels (every input pixel
    gets a gradient), decode with nearest ×2 and the level's skip concatenated. H, W: multiples of 2^(levels − 1)."""
    skips = []
    for i, block in enumerate(enc):
        x = block(x)
        if i < len(enc) - 1:
            skips.append(x)
            x = F.avg_pool2d(x, 2)
    for block in dec:
        x = F.interpolate(x, scale_factor=2.0, mode="nearest")
        x = block(torch.cat([x, skips.pop()], dim=1))
    return x


def pad_to_levels(x: Tensor, levels: int) -> tuple[Tensor, int, int]:
    """``x`` replicate-padded on the bottom and right to multiples of 2^(levels − 1), and its own (h, w)."""
    h, w = x.shape[-2:]
    factor = 2 ** (levels - 1)
    ph, pw = (-h) % factor, (-w) % factor
    return (F.pad(x, (0, pw, 0, ph), mode="replicate") if ph or pw else x), h, w


class LayerGenerator(Pretrained, nn.Module):
    """G(x, label) → edit layer (B, C, H, W) in the layer's range (see the module docstring)."""

    FORMAT = FORMAT
    CONFIG = LayerGeneratorConfig

    def __init__(self, config: LayerGeneratorConfig):
        super().__init__()
        self.config = config
        ch = config.channels
        self.label_emb = (
            nn.Embedding(len(config.vocabulary), config.label_dim) if config.condition == "embedding" else None
        )
        self.enc, self.dec = unet_body(config.base_channels + config.condition_dim, ch, config.blocks)
        self.head = nn.Conv2d(ch[0], config.layer.channels, 1)
        with torch.no_grad():  # the identity edit for every input (module docstring)
            self.head.weight.zero_()
            self.head.bias.copy_(config.layer.identity_preactivation().to(self.head.bias.dtype))

    @property
    def spec(self) -> LayerSpec:
        return self.config.layer

    def label_index(self, labels: Tensor | Sequence[str] | str, batch: int) -> Tensor:
        """(B,) long indices from label strings (one, or one per sample) or an index tensor."""
        vocab = self.config.vocabulary
        if isinstance(labels, Tensor):
            idx = labels.reshape(-1).long()
            if idx.numel() == 1:
                idx = idx.expand(batch)
            if idx.shape != (batch,) or bool(((idx < 0) | (idx >= len(vocab))).any()):
                raise ConditionError(
                    f"label indices {idx.tolist()}; expected {batch} indices in [0, {len(vocab) - 1}]", "labels"
                )
            return idx
        names = [labels] * batch if isinstance(labels, str) else list(labels)
        if len(names) == 1:
            names = names * batch
        if len(names) != batch:
            raise ConditionError(f"got {len(names)} labels for a batch of {batch}; expected 1 or {batch}", "labels")
        out = []
        for name in names:
            if name not in vocab:
                raise ConditionError(f"unknown label {name!r}; expected one of {', '.join(vocab)}", "labels")
            out.append(vocab.index(name))
        return torch.tensor(out, dtype=torch.long)

    def encode_condition(self, idx: Tensor, dtype: torch.dtype) -> Tensor:
        """(B,) label indices → (B, condition_dim) per-sample condition vector."""
        if self.label_emb is not None:
            return self.label_emb(idx).to(dtype)
        x = (idx.to(torch.float32) + 0.5) / len(self.config.vocabulary)  # class id as a float (LMC-SDS suppl.)
        return frequency_encoding(x, self.config.num_freqs).to(dtype)

    def raw(self, base: Tensor, labels: Tensor | Sequence[str] | str) -> Tensor:
        """The head's pre-activation u (B, C, H, W), before the squash."""
        cfg = self.config
        if not isinstance(base, Tensor) or base.dim() != 4 or base.shape[1] != cfg.base_channels:
            got = tuple(base.shape) if isinstance(base, Tensor) else type(base).__name__
            raise LasagnaError(f"base has shape {got}; expected (B, {cfg.base_channels}, H, W) in [0, 1]", "base")
        dtype = self.head.weight.dtype
        b = base.shape[0]
        idx = self.label_index(labels, b).to(self.head.weight.device)
        # Fully convolutional at any size: padded to a multiple of 2^(levels−1), cropped back.
        x, h, w = pad_to_levels(base.to(dtype) * 2 - 1, len(cfg.channels))
        cond = self.encode_condition(idx, dtype)[:, :, None, None].expand(-1, -1, *x.shape[-2:])
        x = run_unet(self.enc, self.dec, torch.cat([x, cond], dim=1))
        return self.head(x)[:, :, :h, :w]

    def forward(self, base: Tensor, labels: Tensor | Sequence[str] | str) -> Tensor:
        """The edit layer (B, C, H, W) for base (B, 3, H, W) in [0, 1] and the labels."""
        return activate(self.raw(base, labels), self.spec)
