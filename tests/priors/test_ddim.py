"""DDIM sampling (lasagna.priors.ddim) against closed-form priors.

``GaussPrior``: data ~ N(m_label, s²·I) per label (the null label has its own mean), whose exact
ε-prediction is E[ε | z_t] = √(1−ᾱ)(z_t − √ᾱ m)/(ᾱ s² + 1 − ᾱ). With s = 0 (a point mass) every
x̂₀ equals m, so DDIM lands exactly on m; with guidance ω it lands on m_u + ω(m_c − m_u).
The deterministic DDIM map is re-implemented in numpy float64 as the reference.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.priors.base import Condition, NoiseSchedule, Prior
from lasagna.priors.ddim import ddim_sample, ddim_timesteps
from lasagna.priors.unet import UNetPrior
from tests.priors.test_unet import randomize, toy_config

SHAPE = (1, 2, 2)


class GaussPrior(Prior):
    """Closed-form prior: per-label means (last entry: the null label), shared std ``s``."""

    def __init__(self, means: dict[str, float], null_mean: float, s: float, T: int = 1000):
        super().__init__()
        self.schedule = NoiseSchedule(T)
        self.vocabulary = tuple(means)
        self.sample_shape = SHAPE
        self.means = torch.tensor([*means.values(), null_mean], dtype=torch.float64)
        self.s = s
        self.calls: list[int] = []

    def _eps(self, z_t, t, label_idx, image):
        self.calls.append(z_t.shape[0])
        ab = self.schedule.alphas_cumprod[t].reshape(-1, 1, 1, 1)  # float64
        m = self.means[label_idx].reshape(-1, 1, 1, 1)
        eps = (1 - ab).sqrt() * (z_t.double() - ab.sqrt() * m) / (ab * self.s**2 + 1 - ab)
        return eps.to(z_t.dtype)


def numpy_ddim(z_T: np.ndarray, m: float, s: float, steps: int, T: int = 1000) -> np.ndarray:
    """Independent float64 DDIM (η = 0) for the Gaussian prior."""
    abar = np.cumprod(1.0 - np.linspace(1e-4, 0.02, T))
    ts = np.unique(np.round(np.linspace(0, T - 1, steps)).astype(int))[::-1]
    z = z_T.astype(np.float64)
    for i, t in enumerate(ts):
        a_t = abar[t]
        a_s = abar[ts[i + 1]] if i + 1 < len(ts) else 1.0
        eps = np.sqrt(1 - a_t) * (z - np.sqrt(a_t) * m) / (a_t * s**2 + 1 - a_t)
        x0 = (z - np.sqrt(1 - a_t) * eps) / np.sqrt(a_t)
        z = np.sqrt(a_s) * x0 + np.sqrt(1 - a_s) * eps
    return z


class TestTimesteps:
    def test_grid(self):
        assert ddim_timesteps(1000, 1) == [999]
        assert ddim_timesteps(1000, 2) == [999, 0]
        ts = ddim_timesteps(1000, 50)
        assert len(ts) == 50 and ts[0] == 999 and ts[-1] == 0 and ts == sorted(ts, reverse=True)
        assert ddim_timesteps(10, 10) == list(range(9, -1, -1))

    @pytest.mark.parametrize("steps", [0, 1001])
    def test_out_of_range(self, steps):
        with pytest.raises(ValueError, match="steps must be in"):
            ddim_timesteps(1000, steps)


class TestDDIMClosedForm:
    @pytest.mark.parametrize("eta", [0.0, 1.0])
    @pytest.mark.parametrize("steps", [1, 7, 50])
    def test_point_mass_is_reached_exactly(self, eta, steps):
        prior = GaussPrior({"a": 0.3}, null_mean=-0.2, s=0.0)
        out = ddim_sample(prior, Condition("a"), steps=steps, eta=eta, batch=3, rng=torch.Generator().manual_seed(0))
        assert out.z.shape == (3, *SHAPE)
        # 1e-4: at t = 999, x̂₀ = (z − √(1−ᾱ) ε̂)/√ᾱ divides a float32 cancellation by √ᾱ ≈ 6e-3.
        torch.testing.assert_close(out.z, torch.full_like(out.z, 0.3), atol=1e-4, rtol=0)
        torch.testing.assert_close(out.image, torch.full_like(out.z, 0.65), atol=1e-4, rtol=0)  # decode = (z + 1)/2

    @pytest.mark.parametrize("omega, expected", [(0.0, -0.2), (1.0, 0.3), (3.0, -0.2 + 3 * 0.5)])
    def test_guidance_convention(self, omega, expected):
        """ε_u + ω(ε_c − ε_u) of two point masses is the point mass at m_u + ω(m_c − m_u)."""
        prior = GaussPrior({"a": 0.3}, null_mean=-0.2, s=0.0)
        out = ddim_sample(prior, Condition("a"), steps=10, omega=omega, batch=2, rng=torch.Generator().manual_seed(0))
        torch.testing.assert_close(out.z, torch.full_like(out.z, expected), atol=1e-4, rtol=0)
        # One network call per step; both branches batched together only when they are needed.
        assert prior.calls == [4 if omega not in (0.0, 1.0) else 2] * 10

    def test_matches_numpy_reference_map(self):
        prior = GaussPrior({"a": 0.4}, null_mean=0.0, s=0.5)
        z_T = torch.randn(16, *SHAPE, generator=torch.Generator().manual_seed(3))
        out = ddim_sample(prior, Condition("a"), steps=50, z_T=z_T, decode=False)
        assert out.image is None
        np.testing.assert_allclose(out.z.double().numpy(), numpy_ddim(z_T.double().numpy(), 0.4, 0.5, 50), atol=2e-5)

    @pytest.mark.parametrize("eta", [0.0, 1.0])
    def test_gaussian_distribution_is_reached(self, eta):
        """Many samples with 100 steps: sample mean and std match N(m, s²) (4σ sampling tolerance
        plus 0.02 for discretisation)."""
        m, s, n = 0.4, 0.5, 2048
        prior = GaussPrior({"a": m}, null_mean=0.0, s=s)
        out = ddim_sample(
            prior, Condition("a"), steps=100, eta=eta, batch=n, rng=torch.Generator().manual_seed(1), decode=False
        )
        x = out.z.double().flatten()
        se = s / np.sqrt(x.numel())
        assert abs(x.mean().item() - m) < 4 * se + 0.02
        assert abs(x.std().item() - s) < 4 * s / np.sqrt(2 * x.numel()) + 0.02

    def test_clip_x0(self):
        """A point mass outside [−1, 1]: unclipped DDIM reaches it, clipped DDIM stops at the bound."""
        prior = GaussPrior({"a": 2.0}, null_mean=0.0, s=0.0)
        free = ddim_sample(prior, Condition("a"), steps=10, rng=torch.Generator().manual_seed(0), decode=False)
        clipped = ddim_sample(prior, Condition("a"), steps=10, clip_x0=True, rng=torch.Generator().manual_seed(0))
        torch.testing.assert_close(free.z, torch.full_like(free.z, 2.0), atol=1e-4, rtol=0)
        torch.testing.assert_close(clipped.z, torch.full_like(clipped.z, 1.0), atol=1e-4, rtol=0)
        assert clipped.image.max() <= 1.0


class TestDDIMBehaviour:
    @pytest.mark.parametrize("eta", [0.0, 0.5])
    def test_seeded_determinism(self, eta):
        prior = GaussPrior({"a": 0.1}, null_mean=0.0, s=0.5)

        def run(seed):
            return ddim_sample(
                prior, Condition("a"), steps=20, eta=eta, batch=4, rng=torch.Generator().manual_seed(seed)
            ).z

        assert torch.equal(run(0), run(0))
        assert not torch.allclose(run(0), run(1))

    def test_batch_sizes(self):
        prior = GaussPrior({"a": 0.1, "b": 0.2}, null_mean=0.0, s=0.5)
        assert ddim_sample(prior, Condition(["a", "b", "a"]), steps=2).z.shape == (3, *SHAPE)
        assert ddim_sample(prior, Condition("a", image=torch.rand(5, 3, 4, 4)), steps=2).z.shape == (5, *SHAPE)
        with pytest.raises(ValueError, match="conflicting batch sizes"):
            ddim_sample(prior, Condition(["a", "b"]), steps=2, batch=3)
        with pytest.raises(ValueError, match="z_T has shape"):
            ddim_sample(prior, Condition("a"), steps=2, z_T=torch.zeros(1, 3, 2, 2))
        with pytest.raises(ValueError, match="conflicting batch sizes"):
            ddim_sample(prior, Condition("a"), steps=2, batch=2, z_T=torch.zeros(1, *SHAPE))
        with pytest.raises(ValueError, match="eta"):
            ddim_sample(prior, Condition("a"), steps=2, eta=-1.0)

    def test_unet_prior_smoke(self):
        prior = randomize(UNetPrior(toy_config()), scale=0.05).eval()
        out = ddim_sample(
            prior,
            Condition(["left", "right"], image=torch.rand(2, 3, 8, 8)),
            steps=5,
            omega=2.0,
            rng=torch.Generator().manual_seed(0),
            clip_x0=True,
        )
        assert out.z.shape == (2, 3, 8, 8) and out.image.shape == (2, 3, 8, 8)
        assert torch.isfinite(out.z).all() and out.image.min() >= 0 and out.image.max() <= 1
