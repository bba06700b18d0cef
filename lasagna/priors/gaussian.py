"""Closed-form priors: Gaussian and Gaussian-mixture data, whose exact denoisers make the losses testable.

Data in the prior's space are x ~ Σ_k w_k N(μ_k, Σ_k) per label (one component per label for
``GaussianPrior``). Under the forward process z_t = √ᾱ x + √(1 − ᾱ) ε (Ho et al. 2020, eq. 4), each
component gives a jointly Gaussian (x, ε, z_t) with

    z_t | k ~ N(√ᾱ μ_k, C_k),   C_k = ᾱ Σ_k + (1 − ᾱ) I,   Cov(ε, z_t | k) = √(1 − ᾱ) I,

so the MMSE ε-prediction a perfectly trained network converges to is, per component,

    E[ε | z_t, k] = √(1 − ᾱ) C_k⁻¹ (z_t − √ᾱ μ_k),
    E[x | z_t, k] = μ_k + √ᾱ Σ_k C_k⁻¹ (z_t − √ᾱ μ_k),

and for a mixture the responsibility-weighted sum, r_k ∝ w_k N(z_t; √ᾱ μ_k, C_k) (Tweedie's formula
ε̂ = −√(1 − ᾱ) ∇ log p_t(z_t) gives the same; the tests check that independently).

The **unconditional branch** (the null label) is, by default, the exact marginal over labels: the
mixture of every label's components with weights π_label · w_k. A real classifier-free-guidance
network learns its unconditional branch separately, so ``unconditional=`` may instead name an
explicit mixture (e.g. one Gaussian) — which keeps the guided SDS fixed point linear, hence in closed
form, for every ω.

Numerics: every closed form runs in float64 on the input's device (covariances are
eigendecomposed once, Σ_k = U diag(λ) Uᵀ, so C_k⁻¹ is a division in the eigenbasis) and is cast back
to the input's dtype. ``.to(dtype)`` on the module does not lower that precision. The conditioning
image of a ``Condition`` is accepted and ignored: these priors depend on the label only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch

from lasagna.errors import ConditionError
from lasagna.priors.base import NoiseSchedule, Prior

#: one mixture component as given by a user: (weight, mean, covariance); mean of shape
#: ``sample_shape`` or (D,); covariance a scalar variance, per-dimension variances (D,) /
#: ``sample_shape`` (diagonal Σ), or a full (D, D) matrix.
Component = tuple[float, torch.Tensor, "torch.Tensor | float"]


class _Mixture:
    """float64 parameters of one Gaussian mixture in the eigenbasis of each component's covariance."""

    def __init__(self, components: Sequence[Component], dim: int, where: str):
        if not components:
            raise ValueError(f"{where}: a mixture needs at least one component, got none")
        weights, means, lams, bases = [], [], [], []
        for i, (w, mean, cov) in enumerate(components):
            w = float(w)
            if not (w > 0 and math.isfinite(w)):
                raise ValueError(f"{where}[{i}]: weight must be a finite number > 0, got {w}")
            mean = torch.as_tensor(mean, dtype=torch.float64).reshape(-1)
            if mean.numel() != dim:
                raise ValueError(f"{where}[{i}]: mean has {mean.numel()} elements; expected {dim}")
            lam, basis = _eig(torch.as_tensor(cov, dtype=torch.float64), dim, f"{where}[{i}]")
            weights.append(w)
            means.append(mean)
            lams.append(lam)
            bases.append(basis)
        w = torch.tensor(weights, dtype=torch.float64)
        self.log_w = (w / w.sum()).log()  # (K,)
        self.mu = torch.stack(means)  # (K, D)
        self.lam = torch.stack(lams)  # (K, D) eigenvalues of Σ_k (the variances when diagonal)
        # (K, D, D) orthonormal eigenvectors as columns, or None when every Σ_k is diagonal
        self.basis = (
            None
            if all(b is None for b in bases)
            else torch.stack([torch.eye(dim, dtype=torch.float64) if b is None else b for b in bases])
        )
        self._cache: dict[torch.device, tuple] = {}

    @property
    def num_components(self) -> int:
        return self.mu.shape[0]

    def on(self, device: torch.device) -> tuple:
        if device not in self._cache:
            move = lambda x: None if x is None else x.to(device)  # noqa: E731
            self._cache[device] = (move(self.log_w), move(self.mu), move(self.lam), move(self.basis))
        return self._cache[device]

    @staticmethod
    def merge(others: Sequence[tuple[float, _Mixture]]) -> _Mixture:
        """The mixture Σ_j π_j · mixture_j (used for the label marginal)."""
        out = object.__new__(_Mixture)
        pis = torch.tensor([p for p, _ in others], dtype=torch.float64)
        log_pi = (pis / pis.sum()).log()
        out.log_w = torch.cat([lp + m.log_w for lp, (_, m) in zip(log_pi, others)])
        out.mu = torch.cat([m.mu for _, m in others])
        out.lam = torch.cat([m.lam for _, m in others])
        dim = out.mu.shape[1]
        if all(m.basis is None for _, m in others):
            out.basis = None
        else:
            eye = torch.eye(dim, dtype=torch.float64)
            out.basis = torch.cat(
                [m.basis if m.basis is not None else eye.expand(m.num_components, dim, dim) for _, m in others]
            )
        out._cache = {}
        return out

    def posterior(self, z_t: torch.Tensor, ab: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """E[ε | z_t] and E[x | z_t] for z_t (n, D), ᾱ (n,), both float64 → (n, D), (n, D)."""
        log_w, mu, lam, basis = self.on(z_t.device)
        sa, s1a = ab.sqrt()[:, None, None], (1 - ab).sqrt()[:, None, None]  # (n, 1, 1)
        r = z_t[:, None, :] - sa * mu[None]  # (n, K, D) z_t − √ᾱ μ_k
        if basis is not None:
            r = torch.einsum("nkd,kde->nke", r, basis)  # coordinates in Σ_k's eigenbasis: Uᵀ r
        c = ab[:, None, None] * lam[None] + (1 - ab)[:, None, None]  # (n, K, D) eigenvalues of C_k
        e = s1a * r / c  # √(1 − ᾱ) C⁻¹ r
        dx = sa * lam[None] * r / c  # √ᾱ Σ C⁻¹ r
        # log w_k + log N(z_t; √ᾱ μ_k, C_k) up to the shared −D/2 log 2π
        logp = log_w[None] - 0.5 * ((r * r / c).sum(-1) + c.log().sum(-1))  # (n, K)
        resp = torch.softmax(logp, dim=1)[..., None]  # (n, K, 1)
        if basis is not None:
            e = torch.einsum("nke,kde->nkd", e, basis)
            dx = torch.einsum("nke,kde->nkd", dx, basis)
        eps = (resp * e).sum(1)
        x0 = (resp * (mu[None] + dx)).sum(1)
        return eps, x0

    def expected_x0(self, z: torch.Tensor, ab: torch.Tensor) -> torch.Tensor:
        """E_ε[E[x | √ᾱ z + √(1 − ᾱ) ε]] for ONE component: μ + ᾱ Σ C⁻¹ (z − μ) (linear in ε, so exact)."""
        _, mu, lam, basis = self.on(z.device)
        d = z - mu[0]  # (n, D)
        if basis is not None:
            d = d @ basis[0]  # Uᵀ d, row-vector form
        a = ab[:, None]
        out = a * lam[0] * d / (a * lam[0] + 1 - a)
        if basis is not None:
            out = out @ basis[0].T
        return mu[0] + out

    def sample(self, n: int, rng: torch.Generator | None) -> torch.Tensor:
        """n draws (n, D) float64 on the CPU."""
        k = torch.multinomial(self.log_w.exp(), n, replacement=True, generator=rng)
        xi = torch.randn((n, self.mu.shape[1]), generator=rng, dtype=torch.float64)
        xi = xi * self.lam[k].clamp_min(0).sqrt()
        if self.basis is not None:
            xi = torch.einsum("nde,ne->nd", self.basis[k], xi)  # U ξ
        return self.mu[k] + xi


def _eig(cov: torch.Tensor, dim: int, where: str) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(eigenvalues (D,), eigenvectors (D, D) or None for a diagonal covariance)."""
    if cov.numel() == 1:
        lam, basis = cov.reshape(1).expand(dim).clone(), None
    elif cov.numel() == dim:
        lam, basis = cov.reshape(dim).clone(), None
    elif cov.shape == (dim, dim):
        if not torch.allclose(cov, cov.T, rtol=1e-10, atol=1e-12):
            raise ValueError(f"{where}: covariance matrix is not symmetric")
        lam, basis = torch.linalg.eigh(cov)
        # eigh of a PSD matrix may return −1e−17 for a zero eigenvalue; that is rounding, not input.
        lam = torch.where(lam.abs() < 1e-12 * max(1.0, float(lam.abs().max())), torch.zeros_like(lam), lam)
    else:
        raise ValueError(
            f"{where}: covariance has shape {tuple(cov.shape)}; expected a scalar, ({dim},) variances or ({dim}, {dim})"
        )
    if not torch.isfinite(lam).all() or (lam < 0).any():
        raise ValueError(
            f"{where}: covariance must be finite and positive semi-definite; smallest eigenvalue {float(lam.min()):.3g}"
        )
    return lam, basis


class GaussianMixturePrior(Prior):
    """Per label, data ~ a Gaussian mixture; exact posterior-mean ε-predictions (see the module docstring).

    ``components``: label → [(weight, mean, covariance), ...]; the mapping's order is the vocabulary.
    ``label_weights``: label → π (default uniform), the label marginal of the unconditional branch.
    ``unconditional``: explicit components for the null label instead of the label marginal.
    """

    def __init__(
        self,
        sample_shape: tuple[int, int, int],
        components: Mapping[str, Sequence[Component]],
        label_weights: Mapping[str, float] | None = None,
        unconditional: Sequence[Component] | None = None,
        schedule: NoiseSchedule | None = None,
    ):
        super().__init__()
        if len(sample_shape) != 3 or any(int(s) < 1 for s in sample_shape):
            raise ValueError(f"sample_shape must be (channels, height, width) of positive ints, got {sample_shape}")
        if not components:
            raise ValueError("components: expected at least one label, got none")
        for lab in components:
            if not isinstance(lab, str) or not lab:
                raise ValueError(
                    f"components: labels must be non-empty strings (the null label is implicit), got {lab!r}"
                )
        self.sample_shape = tuple(int(s) for s in sample_shape)
        self.dim = math.prod(self.sample_shape)
        self.vocabulary = tuple(components)
        self.schedule = schedule if schedule is not None else NoiseSchedule()
        self._labels = [_Mixture(components[lab], self.dim, f"components[{lab!r}]") for lab in self.vocabulary]
        pis = dict.fromkeys(self.vocabulary, 1.0) if label_weights is None else dict(label_weights)
        if set(pis) != set(self.vocabulary):
            raise ValueError(f"label_weights: keys {sorted(pis)} must equal the vocabulary {sorted(self.vocabulary)}")
        for lab, p in pis.items():
            if not (float(p) > 0 and math.isfinite(float(p))):
                raise ValueError(f"label_weights[{lab!r}]: must be a finite number > 0, got {p}")
        if unconditional is None:
            self._uncond = _Mixture.merge([(float(pis[lab]), m) for lab, m in zip(self.vocabulary, self._labels)])
        else:
            self._uncond = _Mixture(unconditional, self.dim, "unconditional")

    # -- the Prior interface ------------------------------------------------------------------
    def _eps(
        self, z_t: torch.Tensor, t: torch.Tensor, label_idx: torch.Tensor, image: torch.Tensor | None
    ) -> torch.Tensor:
        return self.posterior(z_t, t, label_idx)[0]

    # -- closed forms -------------------------------------------------------------------------
    def mixture(self, label_idx: int) -> _Mixture:
        """The mixture of one label index (``len(vocabulary)`` = the unconditional branch)."""
        if label_idx == len(self.vocabulary):
            return self._uncond
        if not 0 <= label_idx < len(self.vocabulary):
            raise ConditionError(f"label index {label_idx} is outside [0, {len(self.vocabulary)}]", "label_idx")
        return self._labels[label_idx]

    def _per_label(
        self, x: torch.Tensor, t: torch.Tensor, label_idx: torch.Tensor | int | None, fn
    ) -> list[torch.Tensor]:
        b = x.shape[0]
        if tuple(x.shape[1:]) != self.sample_shape:
            raise ConditionError(
                f"input has shape {tuple(x.shape)}; expected (B, {', '.join(map(str, self.sample_shape))})", "z"
            )
        if label_idx is None:
            label_idx = len(self.vocabulary)
        idx = torch.as_tensor(label_idx, dtype=torch.long).reshape(-1)
        if idx.numel() == 1:
            idx = idx.expand(b)
        if idx.shape != (b,):
            raise ConditionError(f"label_idx has shape {tuple(idx.shape)}; expected ({b},)", "label_idx")
        flat = x.detach().to(torch.float64).reshape(b, self.dim)
        ab = self.schedule.alpha_bar(t.to(x.device), torch.float64).reshape(b)
        outs = None
        idx_cpu = idx.cpu()
        for lab in idx_cpu.unique().tolist():
            rows = (idx_cpu == lab).nonzero().squeeze(1).to(x.device)
            res = fn(self.mixture(int(lab)), flat[rows], ab[rows])
            res = res if isinstance(res, tuple) else (res,)
            if outs is None:
                outs = [torch.empty_like(flat) for _ in res]
            for o, r in zip(outs, res):
                o[rows] = r
        return [o.reshape(x.shape).to(x.dtype) for o in outs]

    def posterior(
        self, z_t: torch.Tensor, t: torch.Tensor, label_idx: torch.Tensor | int | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(E[ε | z_t], E[x | z_t]) per sample; ``label_idx`` None = the unconditional branch."""
        return tuple(self._per_label(z_t, t, label_idx, lambda m, z, ab: m.posterior(z, ab)))

    def expected_x0(
        self, z: torch.Tensor, t: torch.Tensor, label_idx: torch.Tensor | int | None = None
    ) -> torch.Tensor:
        """E_ε[x̂₀(√ᾱ z + √(1 − ᾱ) ε)] for a clean z: the mean denoised image a corrective b̂ learns.

        Exact for a branch with one component (x̂₀ is affine in ε there): μ + ᾱ Σ C⁻¹ (z − μ). A
        mixture's x̂₀ is not affine in ε and has no closed-form mean, so it is refused.
        """

        def fn(m: _Mixture, zz: torch.Tensor, ab: torch.Tensor) -> torch.Tensor:
            if m.num_components != 1:
                raise ConditionError(
                    f"expected_x0 is closed-form only for a one-component branch; this one has {m.num_components}",
                    "label_idx",
                )
            return m.expected_x0(zz, ab)

        return self._per_label(z, t, label_idx, fn)[0]

    def sample(
        self, n: int, label: str | None = None, rng: torch.Generator | None = None, dtype: torch.dtype = torch.float32
    ) -> torch.Tensor:
        """n data samples (n, C, H, W) of ``label`` (None or "" = the unconditional branch), on the CPU."""
        idx = len(self.vocabulary) if not label else int(self.label_index([label])[0])
        return self.mixture(idx).sample(n, rng).reshape(n, *self.sample_shape).to(dtype)

    def mean(self, label: str | None = None) -> torch.Tensor:
        """The data mean (C, H, W) float64 of a label (None = unconditional)."""
        idx = len(self.vocabulary) if not label else int(self.label_index([label])[0])
        m = self.mixture(idx)
        return (m.log_w.exp()[:, None] * m.mu).sum(0).reshape(self.sample_shape)


class GaussianPrior(GaussianMixturePrior):
    """One Gaussian N(μ_label, Σ_label) per label; the unconditional branch is their π-weighted mixture
    (or, with ``unconditional=(mean, covariance)``, an explicit Gaussian)."""

    def __init__(
        self,
        sample_shape: tuple[int, int, int],
        means: Mapping[str, torch.Tensor],
        covariances: Mapping[str, torch.Tensor | float],
        label_weights: Mapping[str, float] | None = None,
        unconditional: tuple[torch.Tensor, torch.Tensor | float] | None = None,
        schedule: NoiseSchedule | None = None,
    ):
        if set(means) != set(covariances):
            raise ValueError(
                f"means and covariances must have the same labels; got {sorted(means)} vs {sorted(covariances)}"
            )
        super().__init__(
            sample_shape,
            {lab: [(1.0, means[lab], covariances[lab])] for lab in means},
            label_weights=label_weights,
            unconditional=None if unconditional is None else [(1.0, unconditional[0], unconditional[1])],
            schedule=schedule,
        )

    @classmethod
    def random(
        cls,
        vocabulary: Sequence[str] = ("left", "right"),
        sample_shape: tuple[int, int, int] = (3, 4, 4),
        seed: int = 0,
        full: bool = False,
        unconditional: bool = False,
        schedule: NoiseSchedule | None = None,
    ) -> GaussianPrior:
        """A reproducible example: means in [−0.5, 0.5], variances in [0.01, 0.1] (full covariances
        with random eigenvectors when ``full``); ``unconditional`` adds an explicit unconditional
        Gaussian whose variances exceed every label's (so guided SDS has a stable fixed point)."""
        rng = torch.Generator().manual_seed(seed)
        d = math.prod(sample_shape)
        means, covs = {}, {}
        for lab in vocabulary:
            means[lab] = torch.rand(d, generator=rng, dtype=torch.float64) - 0.5
            var = 0.01 + 0.09 * torch.rand(d, generator=rng, dtype=torch.float64)
            if full:
                q, _ = torch.linalg.qr(torch.randn(d, d, generator=rng, dtype=torch.float64))
                covs[lab] = q @ torch.diag(var) @ q.T
                covs[lab] = (covs[lab] + covs[lab].T) / 2
            else:
                covs[lab] = var
        unc = None
        if unconditional:
            mu_u = torch.stack(list(means.values())).mean(0)
            if full:
                top = max(float(torch.linalg.eigvalsh(c).max()) for c in covs.values())
                unc = (mu_u, torch.full((d,), top + 0.05, dtype=torch.float64))
            else:
                unc = (mu_u, torch.stack(list(covs.values())).max(0).values + 0.05)
        return cls(sample_shape, means, covs, unconditional=unc, schedule=schedule)


class ExpectedX0Corrective:
    """The exact b̂ of a one-component Gaussian branch: b̂(z, t) = E_ε[x̂₀ | z, t] (LMC-SDS, Sec. 4).

    LMC-SDS's b̂ is trained to predict the denoiser's output from the clean image; for a deterministic
    model "at best it can learn the mean over all possible ẑ_t" (Alldieck et al.). For a Gaussian
    branch that mean is closed form, so this callable is the perfectly trained corrective. ``branch``
    says which denoiser it mimics: ``"uncond"`` (default; L_lmc compares with the unconditional
    ẑ_t) or ``"cond"`` (uses the ``label_idx`` the loss passes).
    """

    def __init__(self, prior: GaussianMixturePrior, branch: str = "uncond"):
        if branch not in ("uncond", "cond"):
            raise ValueError(f"branch must be 'uncond' or 'cond', got {branch!r}")
        self.prior = prior
        self.branch = branch

    def __call__(
        self,
        z: torch.Tensor,
        t: torch.Tensor,
        cond_image: torch.Tensor | None = None,
        label_idx: torch.Tensor | None = None,
    ) -> torch.Tensor:
        if self.branch == "cond" and label_idx is None:
            raise ConditionError("branch='cond' needs the label_idx the loss passes; got None", "label_idx")
        return self.prior.expected_x0(z, t, None if self.branch == "uncond" else label_idx)
