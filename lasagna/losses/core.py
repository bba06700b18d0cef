"""The shared core of every score-distillation loss: timesteps, weighting, CFG, gradient injection.

One place for each rule, so the five losses (sds, lmc_sds, dds, nfsd, ms_sds) differ only in the
gradient they compute:

* ``TimestepSampler``: per-sample t ~ U(t_min, t_max) in the papers' continuous notation (default
  0.02–0.98, DreamFusion and the LMC-SDS supplementary), mapped to the prior's integer steps by
  ``NoiseSchedule.continuous_to_index`` (round(u·(T − 1)): 0.02 → 20, 0.98 → 979 for T = 1000).
  Optional annealing of t_max over optimisation steps (linear or cosine decay to ``t_max_final``),
  a common SDS schedule (e.g. DreamTime; threestudio's ``max_step_percent`` ramps).
* ``weight``: w(t) ∈ {1, 1 − ᾱ_t (DreamFusion: σ_t²), √ᾱ_t·(1 − ᾱ_t) (Fantasia3D; threestudio's
  "fantasia3d")}. DreamFusion also absorbs ∂z_t/∂z = √ᾱ_t I into w(t) (its footnote to eq. 3); so
  do we: every gradient here is with respect to the clean z, without a √ᾱ_t factor.
* ``cfg``: the ONE guidance convention ε̂ = ε_u + ω(ε_c − ε_u) (LMC-SDS eq. 4/5). Code written in
  the "text-first" form ε_c + s(ε_c − ε_u) uses ω = s + 1.
* ``inject``: turns a gradient g into a surrogate whose autograd derivative in z is exactly g,
  without backpropagating through the prior.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator

from lasagna.numerics import reduction_dtype
from lasagna.priors.base import NoiseSchedule, cfg  # noqa: F401  (cfg: re-exported, the one CFG convention)

Weighting = Literal["uniform", "1-alpha_bar", "sqrt_alpha_bar(1-alpha_bar)"]


# -- timesteps --------------------------------------------------------------------------------
class TimestepOptions(BaseModel):
    """t ~ U(t_min, t_max(step)) per sample, t in [0, 1] (the papers' notation)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    t_min: float = Field(0.02, ge=0.0, le=1.0)
    t_max: float = Field(0.98, ge=0.0, le=1.0)
    anneal: Literal["none", "linear", "cosine"] = "none"
    t_max_final: float | None = Field(None, ge=0.0, le=1.0, description="t_max after anneal_steps")
    anneal_steps: int = Field(0, ge=0)

    @model_validator(mode="after")
    def _order(self) -> TimestepOptions:
        if self.t_min > self.t_max:
            raise ValueError(f"t_min ({self.t_min}) must be <= t_max ({self.t_max})")
        if self.anneal != "none":
            if self.t_max_final is None or self.anneal_steps < 1:
                raise ValueError(f"anneal={self.anneal!r} needs t_max_final and anneal_steps >= 1")
            if not self.t_min <= self.t_max_final <= self.t_max:
                raise ValueError(
                    f"t_max_final ({self.t_max_final}) must lie in [t_min, t_max] = [{self.t_min}, {self.t_max}]"
                )
        return self


class TimestepSampler:
    """Draws per-sample integer timesteps for a schedule (see ``TimestepOptions``)."""

    def __init__(self, options: TimestepOptions | None = None):
        self.options = options if options is not None else TimestepOptions()

    def t_max_at(self, step: int | None) -> float:
        o = self.options
        if o.anneal == "none":
            return o.t_max
        if step is None:
            raise ValueError(f"timesteps anneal t_max ({o.anneal}) over steps; pass step= to the loss")
        frac = min(max(step, 0) / o.anneal_steps, 1.0)
        if o.anneal == "linear":
            decay = frac
        else:  # cosine: slow start and end
            decay = 0.5 * (1.0 - math.cos(math.pi * frac))
        return o.t_max - (o.t_max - o.t_max_final) * decay

    def sample(
        self,
        batch: int,
        schedule: NoiseSchedule,
        rng: torch.Generator | None,
        device: torch.device | str = "cpu",
        step: int | None = None,
    ) -> torch.Tensor:
        """(batch,) long timesteps in [round(t_min·(T−1)), round(t_max·(T−1))]."""
        lo, hi = self.options.t_min, self.t_max_at(step)
        rng_device = rng.device if rng is not None else torch.device(device)
        u = lo + (hi - lo) * torch.rand((batch,), generator=rng, device=rng_device, dtype=torch.float64)
        return schedule.continuous_to_index(u).to(device)


# -- weighting and guidance -------------------------------------------------------------------
def weight(
    schedule: NoiseSchedule, t: torch.Tensor, kind: Weighting, dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """w(t) per sample (B,), computed from the float64 ᾱ table and cast once."""
    ab = schedule.alpha_bar(t, torch.float64)
    if kind == "uniform":
        w = torch.ones_like(ab)
    elif kind == "1-alpha_bar":
        w = 1 - ab
    elif kind == "sqrt_alpha_bar(1-alpha_bar)":
        w = ab.sqrt() * (1 - ab)
    else:
        raise ValueError(f"unknown weighting {kind!r}; expected uniform, 1-alpha_bar or sqrt_alpha_bar(1-alpha_bar)")
    return w.to(dtype)


def expand(a: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """(B,) -> (B, 1, 1, 1) for broadcasting against a batch of images."""
    return a.reshape(a.shape + (1,) * (like.dim() - a.dim()))


# -- gradient injection -----------------------------------------------------------------------
@dataclass
class Diagnostics:
    """What one loss evaluation did; every tensor is detached.

    ``grad``: the gradient injected into z (after nan_to_num and the optional clamp), (B, C, h, w).
    ``grad_norm``: its L2 norm per sample (B,). ``t``: integer timesteps (B,).
    ``non_finite``: how many elements of the raw gradient were NaN/±inf (and injected as 0).
    ``clamped``: how many elements the clamp changed. ``components``: the method's named terms,
    scaled like ``grad`` (their sum is the gradient before nan_to_num and clamp), e.g. SDS's
    {"cond", "proj"} (LMC-SDS eq. 6; {"guided"} at ω = 1). ``noise``: the ε draws used, by name.
    """

    grad: torch.Tensor
    grad_norm: torch.Tensor
    t: torch.Tensor | None
    non_finite: torch.Tensor
    clamped: torch.Tensor
    components: dict[str, torch.Tensor] = field(default_factory=dict)
    noise: dict[str, torch.Tensor] = field(default_factory=dict)

    def summary(self) -> dict[str, float]:
        """Plain floats for a log line (this synchronises with the device)."""
        out = {
            "grad_norm": float(self.grad_norm.mean()),
            "non_finite": int(self.non_finite),
            "clamped": int(self.clamped),
        }
        if self.t is not None:
            out["t_mean"] = float(self.t.double().mean())
        for name, c in self.components.items():
            out[f"norm_{name}"] = float(_norms(c).mean())
        return out


def _norms(x: torch.Tensor) -> torch.Tensor:
    return x.detach().to(reduction_dtype(x.dtype)).flatten(1).norm(dim=1)


def inject(
    z: torch.Tensor,
    grad: torch.Tensor,
    clamp: float | None = None,
    *,
    t: torch.Tensor | None = None,
    components: dict[str, torch.Tensor] | None = None,
    noise: dict[str, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, Diagnostics]:
    """A scalar surrogate whose derivative with respect to ``z`` is exactly ``grad``.

    The target trick, loss = ½‖z − sg(z − g)‖² (sg = stop-gradient), has derivative
    z − (z − g) = g — but in floating point z − (z − g) ≠ g. We build the same value ½‖g‖² and
    the same derivative as

        loss = Σ z·sg(g) − Σ sg(z)·sg(g) + ½‖sg(g)‖²

    whose first term differentiates to g exactly and whose other terms are constants (the first two
    are the same float computation, so they cancel exactly). The sum runs over the batch, so each
    sample receives its own g (a caller wanting the batch mean divides the loss by B).

    Before anything else, non-finite elements of g are counted and replaced by 0 (they contribute no
    gradient; ``Diagnostics.non_finite`` reports them), then g is clamped to [−clamp, clamp] if asked.
    The VALUE of the surrogate is ½‖g‖², not a measure of quality; watch ``grad_norm`` instead.
    """
    if grad.shape != z.shape:
        raise ValueError(f"inject: grad has shape {tuple(grad.shape)}; expected z's shape {tuple(z.shape)}")
    if clamp is not None and not clamp > 0:
        raise ValueError(f"inject: clamp must be > 0 or None, got {clamp}")
    g = grad.detach()
    finite = torch.isfinite(g)
    non_finite = (~finite).sum()
    g = torch.where(finite, g, torch.zeros((), dtype=g.dtype, device=g.device))
    clamped = torch.zeros((), dtype=torch.long, device=g.device)
    if clamp is not None:
        clamped = (g.abs() > clamp).sum()
        g = g.clamp(-clamp, clamp)
    g = g.to(z.dtype)
    loss = (z * g).sum() - (z.detach() * g).sum() + 0.5 * (g * g).sum()
    diag = Diagnostics(
        grad=g,
        grad_norm=_norms(g),
        t=t,
        non_finite=non_finite,
        clamped=clamped,
        components={k: v.detach() for k, v in (components or {}).items()},
        noise={k: v.detach() for k, v in (noise or {}).items()},
    )
    return loss, diag
