"""The Prior interface: a conditional denoiser with its noise schedule, called in inference mode.

Every prior (closed-form Gaussian, the bundled pixel UNet, a diffusers Stable-Diffusion adapter)
exposes the same three things to the losses:

* ``schedule``: the variance-preserving schedule, ᾱ_t built in float64 and cast once per dtype;
* ``encode(x)`` / ``decode(z)``: image in [0, 1] (B, 3, H, W) ↔ the space the denoiser works in
  (pixels in [−1, 1] for pixel priors; VAE latents for latent priors). ``encode`` is differentiable:
  the distillation gradient flows through it into the composite;
* ``predict(z_t, t, cond, branches)``: ε-predictions for several condition branches in ONE batched
  network pass (classifier-free guidance needs the conditional and unconditional branch).

Conventions (see docs/ARCHITECTURE.md and ../shared/DESIGN.md):
* t is an integer timestep tensor of shape (B,) in [0, T − 1] (T = ``schedule.num_steps``), one per
  sample, so every t-dependent rule is a per-sample mask.
* z_t = √ᾱ_t z + √(1 − ᾱ_t) ε (Ho et al. 2020, eq. 4); x̂₀ = (z_t − √(1 − ᾱ_t) ε̂)/√ᾱ_t.
* One CFG convention: ε̂ = ε_u + ω(ε_c − ε_u). (The "text-first" form ε_c + s(ε_c − ε_u) is ω = s + 1.)
* Unconditional = the null label with the conditioning image kept (as ControlNet guidance does).
"""

from __future__ import annotations

import abc
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import nn

from lasagna.errors import ConditionError
from lasagna.numerics import SCHEDULE_EPS

Branch = Literal["cond", "uncond", "negative"]


@dataclass
class Condition:
    """What the prior is conditioned on, for a batch.

    ``labels``: one label per sample (or one for all) from the prior's vocabulary, e.g. ``"left"`` of
    "A photo of an object with [r] lighting". ``image``: optional ControlNet-style conditioning image
    (B, C, H, W) in [0, 1], e.g. the base layer; kept in the unconditional branch.
    ``negative``: optional labels for a negative branch (NFSD's negative prompt; DDS's source prompt).
    """

    labels: Sequence[str] | str
    image: torch.Tensor | None = None
    negative: Sequence[str] | str | None = None

    def label_list(self, batch: int) -> list[str]:
        return _broadcast_labels(self.labels, batch, "condition.labels")

    def negative_list(self, batch: int) -> list[str]:
        if self.negative is None:
            raise ConditionError("this loss needs a negative condition; none was given", "condition.negative")
        return _broadcast_labels(self.negative, batch, "condition.negative")


def _broadcast_labels(labels: Sequence[str] | str, batch: int, where: str) -> list[str]:
    if isinstance(labels, str):
        return [labels] * batch
    labels = list(labels)
    if len(labels) == 1:
        return labels * batch
    if len(labels) != batch:
        raise ConditionError(f"got {len(labels)} labels for a batch of {batch}; expected 1 or {batch}", where)
    return labels


class NoiseSchedule:
    """A variance-preserving DDPM schedule: ᾱ_t in float64, cast once per (dtype, device).

    ``kind="linear"``: β linear in [β_start, β_end] (Ho et al. 2020); ``"scaled_linear"``: linear in √β
    (Stable Diffusion); ``"cosine"``: Nichol & Dhariwal 2021, eq. 17, β clipped at 0.999.
    """

    def __init__(
        self,
        num_steps: int = 1000,
        kind: Literal["linear", "scaled_linear", "cosine"] = "linear",
        beta_start: float = 1e-4,
        beta_end: float = 0.02,
    ):
        if num_steps < 2:
            raise ValueError(f"num_steps must be >= 2, got {num_steps}")
        self.num_steps = num_steps
        self.kind = kind
        self.beta_start = beta_start
        self.beta_end = beta_end
        if kind == "linear":
            betas = torch.linspace(beta_start, beta_end, num_steps, dtype=torch.float64)
        elif kind == "scaled_linear":
            betas = torch.linspace(beta_start**0.5, beta_end**0.5, num_steps, dtype=torch.float64) ** 2
        elif kind == "cosine":
            s = 0.008
            steps = torch.arange(num_steps + 1, dtype=torch.float64) / num_steps
            f = torch.cos((steps + s) / (1 + s) * math.pi / 2) ** 2
            betas = (1 - f[1:] / f[:-1]).clamp(max=0.999)
        else:
            raise ValueError(f"unknown schedule kind {kind!r}; expected linear, scaled_linear or cosine")
        self.betas = betas
        self.alphas_cumprod = torch.cumprod(1.0 - betas, dim=0)  # (T,) float64
        self._cast: dict[tuple[torch.dtype, torch.device], torch.Tensor] = {}

    def config(self) -> dict:
        return {
            "num_steps": self.num_steps,
            "kind": self.kind,
            "beta_start": self.beta_start,
            "beta_end": self.beta_end,
        }

    def alpha_bar(self, t: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """ᾱ_t for integer timesteps t (B,), cast once per dtype/device and cached."""
        key = (dtype, t.device)
        table = self._cast.get(key)
        if table is None:
            table = self._cast[key] = self.alphas_cumprod.to(device=t.device, dtype=dtype)
        return table[t.long()]

    def continuous_to_index(self, u: torch.Tensor) -> torch.Tensor:
        """Map t ∈ [0, 1] (the papers' notation, e.g. t ~ U(0.02, 0.98)) to an integer step."""
        return (u * (self.num_steps - 1)).round().long().clamp(0, self.num_steps - 1)

    # Eq. 4 of Ho et al. (2020) and its inversions. Broadcasting helper: (B,) -> (B, 1, 1, 1).
    def add_noise(self, z: torch.Tensor, eps: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        ab = _expand(self.alpha_bar(t, z.dtype), z)
        return ab.sqrt() * z + (1 - ab).sqrt() * eps

    def x0_from_eps(self, z_t: torch.Tensor, eps: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        ab = _expand(self.alpha_bar(t, z_t.dtype), z_t)
        return (z_t - (1 - ab).sqrt() * eps) / ab.sqrt().clamp_min(SCHEDULE_EPS)

    def eps_from_x0(self, z_t: torch.Tensor, x0: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        ab = _expand(self.alpha_bar(t, z_t.dtype), z_t)
        return (z_t - ab.sqrt() * x0) / (1 - ab).sqrt().clamp_min(SCHEDULE_EPS)

    def eps_from_v(self, z_t: torch.Tensor, v: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """v-prediction (Salimans & Ho 2022): v = √ᾱ ε − √(1−ᾱ) x₀ ⇒ ε = √ᾱ v + √(1−ᾱ) z_t."""
        ab = _expand(self.alpha_bar(t, z_t.dtype), z_t)
        return ab.sqrt() * v + (1 - ab).sqrt() * z_t


def cfg(eps_u: torch.Tensor, eps_c: torch.Tensor, omega: float) -> torch.Tensor:
    """Classifier-free guidance ε_u + ω(ε_c − ε_u) (Ho & Salimans 2022; LMC-SDS eq. 5): the one CFG
    convention of the package (the "text-first" form ε_c + s(ε_c − ε_u) is ω = s + 1)."""
    return eps_u + omega * (eps_c - eps_u)


def _expand(a: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return a.reshape(a.shape + (1,) * (like.dim() - a.dim()))


@dataclass
class Prediction:
    """ε-predictions per branch, all from one batched pass; each (B, C, h, w) in the prior's dtype."""

    eps: dict[str, torch.Tensor] = field(default_factory=dict)


class Prior(nn.Module, abc.ABC):
    """A conditional diffusion prior. Subclasses implement ``_eps`` (the raw batched network call)."""

    schedule: NoiseSchedule
    vocabulary: tuple[str, ...]
    #: the (channels, height, width) of the denoiser's space, e.g. (3, 32, 32) or (4, 64, 64) latents
    sample_shape: tuple[int, int, int]

    def label_index(self, labels: Sequence[str]) -> torch.Tensor:
        """Indices into the vocabulary; the null (unconditional) label is ``len(vocabulary)``."""
        out = []
        for lab in labels:
            if lab is None or lab == "":
                out.append(len(self.vocabulary))
                continue
            try:
                out.append(self.vocabulary.index(lab))
            except ValueError:
                raise ConditionError(
                    f"unknown label {lab!r}; expected one of {', '.join(self.vocabulary)}", "condition.labels"
                ) from None
        return torch.tensor(out, dtype=torch.long)

    def label_tensor(self, labels: Sequence[str]) -> torch.Tensor:
        """What ``_eps`` takes for ``labels``: vocabulary indices (``label_index``), or another encoding in a
        prior that conditions on something else (a light direction: ``UNetPrior`` with ``directions``)."""
        return self.label_index(labels)

    def null_tensor(self, batch: int) -> torch.Tensor:
        """What ``_eps`` takes for the null label (the unconditional branch), ``batch`` times."""
        return torch.full((batch,), len(self.vocabulary), dtype=torch.long)

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Image in [0, 1] → denoiser space (differentiable). Pixel priors: 2x − 1."""
        return x * 2 - 1

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Denoiser space → image in [0, 1] (not clamped)."""
        return (z + 1) / 2

    @abc.abstractmethod
    def _eps(
        self, z_t: torch.Tensor, t: torch.Tensor, label_idx: torch.Tensor, image: torch.Tensor | None
    ) -> torch.Tensor:
        """The raw network call: ε̂(z_t, t, label, image) for a batch; label_idx may be the null index."""

    def predict(
        self,
        z_t: torch.Tensor,
        t: torch.Tensor,
        cond: Condition,
        branches: Sequence[Branch] = ("cond", "uncond"),
    ) -> Prediction:
        """ε̂ for each requested branch in ONE batched network call (concatenated along the batch)."""
        eps = self.predict_many([(z_t, br) for br in branches], t, cond)
        return Prediction(eps=dict(zip(branches, eps)))

    def predict_many(
        self,
        queries: Sequence[tuple[torch.Tensor, Branch]],
        t: torch.Tensor,
        cond: Condition,
    ) -> list[torch.Tensor]:
        """ε̂ for several ``(z_t, branch)`` queries in ONE batched network call; one (B, C, h, w) per query.

        Every query shares the per-sample timesteps ``t`` (B,) and the conditioning image; the noisy
        inputs may differ. Losses that need the denoiser at two noisy images (LMC-SDS with a fixed ε
        in L_cond and a fresh ε in L_lmc; DDS's target and source) still pay one network pass.

        The network runs under ``torch.inference_mode()`` (no autograd bookkeeping for its
        activations, and no way for a gradient to reach the prior); the outputs are then cloned
        outside inference mode, once, so callers get ordinary tensors they may combine with tensors
        that require grad (inference tensors cannot be saved for backward). The clone copies only the
        (n·B, C, h, w) output, negligible next to the network pass.
        """
        if not queries:
            raise ValueError("predict_many: expected at least one (z_t, branch) query, got none")
        b = queries[0][0].shape[0]
        if t.shape != (b,):
            raise ValueError(f"predict: t has shape {tuple(t.shape)}; expected ({b},), one timestep per sample")
        if cond.image is not None and cond.image.shape[0] != b:
            raise ConditionError(
                f"image has batch {cond.image.shape[0]}; expected {b} (one per sample)", "condition.image"
            )
        idx, zs = [], []
        for z_t, br in queries:
            if z_t.shape != queries[0][0].shape:
                raise ValueError(f"predict_many: z_t shapes differ: {tuple(z_t.shape)} vs {tuple(queries[0][0].shape)}")
            if br == "cond":
                idx.append(self.label_tensor(cond.label_list(b)))
            elif br == "uncond":
                idx.append(self.null_tensor(b))
            elif br == "negative":
                idx.append(self.label_tensor(cond.negative_list(b)))
            else:
                raise ValueError(f"unknown branch {br!r}; expected cond, uncond or negative")
            zs.append(z_t.detach())
        n = len(queries)
        z0 = queries[0][0]
        with torch.inference_mode():
            zz = torch.cat(zs, dim=0)
            tt = t.repeat(n)
            img = None if cond.image is None else cond.image.detach().repeat(n, *([1] * (cond.image.dim() - 1)))
            eps = self._eps(zz, tt, torch.cat(idx).to(z0.device), img)
        return list(eps.clone().chunk(n, dim=0))
