"""LMC-SDS: Score Distillation Sampling with Learned Manifold Corrective (Alldieck et al., ECCV 2024).

SDS's gradient splits into L_cond + L_proj (eq. 6). L_proj = ε_u − ε = √ᾱ/√(1−ᾱ)·(z − ẑ_t) (eq. 7)
pulls z towards the denoiser's estimate ẑ_t, whose timestep-dependent frequency bias b (eq. 8)
marks detail for removal — the blur of low-guidance SDS. LMC-SDS replaces it:

    ∇_z L_LMC-SDS = (1/ω) · [ L_cond + L_lmc ]                                       (Sec. 5)
    L_cond = ω (ε_φ(z_t^c, y, t) − ε_φ(z_t^c, t))                                    (eq. 6b)
    L_lmc  = b̃(z, t) − ẑ_t,    ẑ_t = x̂₀(z_t^l) = (z_t^l − √(1−ᾱ) ε_φ(z_t^l, t)) / √ᾱ  (eq. 9)
    b̃     = σ(ẑ_t)/σ(b̂) · (b̂ − μ(b̂)) + μ(b̂),   b̂ = b̂_ψ(z, t)                   (eq. 10 "absorbed")

Interpretations (the paper leaves these implicit; each is a choice documented here):

1. **ẑ_t is the unconditional estimate.** Eq. 7 rewrites L_proj, which uses ε_φ(z_t, t) (no y);
   L_lmc replaces L_proj, so ẑ_t comes from the unconditional branch (in Lasagna: null label,
   conditioning image kept). The network pass for it is the one L_cond already needs.
2. **Units.** L_cond is in ε units, L_lmc in x̂₀ (image) units: the paper drops the √ᾱ/√(1−ᾱ)
   factor of eq. 7 ("we can further improve visual fidelity"); ``lmc_weighting="sqrt_snr"``
   restores it, which makes L_lmc = L_proj exactly when b̃ = z.
3. **The normalisation of eq. 10 in eq. 9.** "Predicting in a normalized space naturally requires to
   perform the same operation in Eq. 9, which we assume to be absorbed into b̂": b̂'s output is
   centred by ITS OWN mean, rescaled to the standard deviation of the CURRENT sample ẑ_t, and keeps
   its own mean μ(b̂) — only contrast is matched, not brightness. Statistics are per image over
   (C, h, w) ("agnostic to the global image statistics"), exactly as L_k trains b̂
   (corrective.py); ``normalize="none"`` disables it. σ is the population std, guarded by
   ``numerics.STD_EPS`` (a constant b̂ has σ = 0; ``corrective.mean_std`` clamps the variance, so even a
   gradient through it would be finite).
   Consequence worth knowing: even a perfect b̂ = E_ε[ẑ_t] leaves E[L_lmc] =
   (E σ(ẑ_t)/σ(b̂) − 1)(b̂ − μ(b̂)) ≠ 0, a contrast term, because E σ(ẑ_t) ≥ σ(E ẑ_t) (σ is convex);
   without normalisation E[L_lmc] = 0 exactly for that b̂ (tests/losses/test_lmc_sds.py).
4. **Fixed ε only in L_cond** ("Increasing sample diversity"): with ``fixed_eps=True`` the ε of
   L_cond is drawn once per loss instance (per batch shape) — from ``fixed_eps_seed`` if given,
   else from the first call's rng — and reused at every step; the ε of L_lmc is drawn anew
   each step. Then L_cond and L_lmc see different noisy images z_t^c ≠ z_t^l, and the three
   denoiser evaluations (cond and uncond at z_t^c, uncond at z_t^l) still run in ONE batched pass.
   Without it both terms share one ε and one pass of two branches.
5. **1/ω.** The total is scaled by 1/ω by default (``scale="inv_guidance"``), so the gradient is
   (ε_c − ε_u) + L_lmc/ω. ω = 0 (no conditional term) is then undefined and refused with an error
   naming ``scale="none"``, under which ω = 0 gives L_lmc alone. Negative ω is refused too: 1/ω
   would flip the manifold term.
6. **b̂'s inputs.** ``corrective(z, t, cond_image=, label_idx=)`` receives the clean z in the prior's
   space, the integer timesteps t (B,) of the prior's schedule, the condition's image and the label
   indices (the null index for unconditional samples); it runs under ``torch.no_grad()`` (the paper
   omits b̂'s Jacobian) and must return z's shape. Any callable works; ``Corrective``
   (corrective.py) is the paper's trained network, ``SpectralCorrective`` (spectral.py) a per-t
   linear frequency response fitted in closed form — the bundled default, because a b̂ able to
   predict the scene cancels the manifold pull along with the bias (spectral.py's docstring).
   With no corrective the loss refuses to run: there is no sensible default (b̂ = z,
   ``identity_corrective``, is a baseline, not LMC-SDS).

Weighting: w(t) = 1 by default (the paper omits w(t) "in the sequel").
"""

from __future__ import annotations

from typing import Literal, Protocol

import torch

from lasagna.errors import LasagnaError
from lasagna.losses.base import LossOptions, ScoreLoss, Terms, register_loss
from lasagna.losses.core import Weighting, expand
from lasagna.losses.corrective import rescale_to_target_std
from lasagna.priors.base import Condition, Prior
from lasagna.priors.nn import randn

Normalize = Literal["image", "none"]


class CorrectiveFn(Protocol):
    """b̂(z, t): the clean image's expected denoised version, in the prior's space (eq. 9)."""

    def __call__(
        self,
        z: torch.Tensor,
        t: torch.Tensor,
        cond_image: torch.Tensor | None = None,
        label_idx: torch.Tensor | None = None,
    ) -> torch.Tensor: ...


def identity_corrective(
    z: torch.Tensor, t: torch.Tensor, cond_image: torch.Tensor | None = None, label_idx: torch.Tensor | None = None
) -> torch.Tensor:
    """The trivial b̂ = z (a baseline: L_lmc is then L_proj without its √ᾱ/√(1−ᾱ) factor, up to eq. 10)."""
    return z


# -- eq. 10's normalisation, as eq. 9 uses it -------------------------------------------------
def normalize_like(b_hat: torch.Tensor, z_hat: torch.Tensor, normalize: Normalize = "image") -> torch.Tensor:
    """σ(ẑ)/σ(b̂) · (b̂ − μ(b̂)) + μ(b̂) per image: b̂ with ẑ's contrast and its own mean (LMC-SDS eq. 10).

    Exactly the operation L_k trains b̂ with (``corrective.rescale_to_target_std``; the paper: "the
    same operation in Eq. 9"), so it is imported from there rather than written twice.
    """
    if normalize == "none":
        return b_hat
    if normalize != "image":
        raise ValueError(f"unknown normalize {normalize!r}; expected image or none")
    return rescale_to_target_std(b_hat, z_hat)


# -- the loss -------------------------------------------------------------------------------------
class LMCSDSOptions(LossOptions):
    weighting: Weighting = "uniform"
    scale: Literal["none", "inv_guidance"] = "inv_guidance"
    fixed_eps: bool = False
    fixed_eps_seed: int | None = None
    normalize: Normalize = "image"
    lmc_weighting: Literal["none", "sqrt_snr"] = "none"


@register_loss("lmc-sds")
class LMCSDS(ScoreLoss):
    """L_cond + L_lmc with a manifold corrective b̂ (see the module docstring)."""

    Options = LMCSDSOptions

    def __init__(
        self, corrective: CorrectiveFn | None = None, options: LMCSDSOptions | dict | None = None, **overrides
    ):
        super().__init__(options, **overrides)
        if corrective is None:
            raise LasagnaError(
                "no corrective b̂ given; expected a Corrective or SpectralCorrective "
                "(lasagna.catalogue.load_corrective), or any callable "
                "b̂(z, t, cond_image=, label_idx=)); identity_corrective is the b̂ = z baseline",
                "lmc-sds.corrective",
            )
        if not callable(corrective):
            raise LasagnaError(f"corrective must be callable, got {type(corrective).__name__}", "lmc-sds.corrective")
        self.corrective = corrective
        self._fixed: dict[tuple, torch.Tensor] = {}

    def reset_fixed_noise(self) -> None:
        """Forget the fixed ε of L_cond; the next call draws a new one."""
        self._fixed.clear()

    def fixed_noise(
        self, shape: tuple[int, ...], rng: torch.Generator | None, device: torch.device, dtype: torch.dtype
    ) -> torch.Tensor:
        """The ε of L_cond reused at every step (drawn once per shape, device and dtype)."""
        key = (shape, str(device), dtype)
        if key not in self._fixed:
            seed = self.options.fixed_eps_seed
            noise_rng = rng if seed is None else torch.Generator(device="cpu").manual_seed(seed)
            self._fixed[key] = randn(shape, noise_rng, device, dtype)
        return self._fixed[key]

    def terms(
        self, z: torch.Tensor, t: torch.Tensor, prior: Prior, cond: Condition, omega: float, rng: torch.Generator | None
    ) -> Terms:
        sched, shape = prior.schedule, tuple(z.shape)
        # 1. L_lmc's ε is fresh every step.
        eps_l = randn(shape, rng, z.device, z.dtype)
        z_t_l = sched.add_noise(z, eps_l, t)
        # 2. One batched prior pass: cond + uncond at z_t^c (L_cond), uncond at z_t^l (ẑ_t for L_lmc).
        if self.options.fixed_eps:
            eps_c = self.fixed_noise(shape, rng, z.device, z.dtype)
            z_t_c = sched.add_noise(z, eps_c, t)
            e_c, e_u, e_u_l = prior.predict_many([(z_t_c, "cond"), (z_t_c, "uncond"), (z_t_l, "uncond")], t, cond)
        else:
            eps_c = eps_l
            e_c, e_u = prior.predict_many([(z_t_l, "cond"), (z_t_l, "uncond")], t, cond)
            e_u_l = e_u
        l_cond = omega * (e_c.to(z.dtype) - e_u.to(z.dtype))  # eq. 6b
        z_hat = sched.x0_from_eps(z_t_l, e_u_l.to(z.dtype), t)  # ẑ_t, eq. 7/9
        # 3. The corrective b̂(z, t), without its Jacobian (eq. 9), normalised as in eq. 10.
        label_idx = prior.label_index(cond.label_list(shape[0])).to(z.device)
        with torch.no_grad():
            b_hat = self.corrective(z, t, cond_image=cond.image, label_idx=label_idx)
        if not isinstance(b_hat, torch.Tensor) or tuple(b_hat.shape) != shape:
            got = tuple(b_hat.shape) if isinstance(b_hat, torch.Tensor) else type(b_hat).__name__
            raise LasagnaError(f"corrective returned {got}; expected z's shape {shape}", "lmc-sds.corrective")
        b_tilde = normalize_like(b_hat.detach().to(z.dtype), z_hat, self.options.normalize)
        l_lmc = b_tilde - z_hat  # eq. 9
        if self.options.lmc_weighting == "sqrt_snr":
            ab = sched.alpha_bar(t, torch.float64)
            l_lmc = l_lmc * expand((ab / (1 - ab)).sqrt().to(z.dtype), z)
        return Terms(components={"cond": l_cond, "lmc": l_lmc}, noise={"cond": eps_c, "lmc": eps_l})
