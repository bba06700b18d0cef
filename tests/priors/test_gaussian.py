"""GaussianPrior / GaussianMixturePrior: the closed-form reference priors, checked against numpy
linear algebra (tests/losses/reference.py) and Tweedie's formula via torch.distributions."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.errors import ConditionError, LasagnaError
from lasagna.priors import (
    Condition,
    ExpectedX0Corrective,
    GaussianMixturePrior,
    GaussianPrior,
    Prior,
    available_priors,
    get_prior,
    register_prior,
)
from tests.losses import reference as ref

SHAPE = (3, 2, 2)
D = 12


def _spd(rng: np.random.Generator, lo: float = 0.02, hi: float = 0.3) -> np.ndarray:
    q, _ = np.linalg.qr(rng.standard_normal((D, D)))
    return q @ np.diag(rng.uniform(lo, hi, D)) @ q.T


@pytest.fixture(scope="module")
def mixture_setup():
    """Two labels, two components each (one full covariance, one diagonal), non-uniform label weights."""
    rng = np.random.default_rng(3)
    comps = {
        "left": [
            (0.3, rng.uniform(-0.6, 0.6, D), _spd(rng)),
            (0.7, rng.uniform(-0.6, 0.6, D), rng.uniform(0.02, 0.3, D)),
        ],
        "right": [
            (1.0, rng.uniform(-0.6, 0.6, D), _spd(rng)),
            (2.0, rng.uniform(-0.6, 0.6, D), rng.uniform(0.02, 0.3, D)),
        ],
    }
    pis = {"left": 0.25, "right": 0.75}
    prior = GaussianMixturePrior(
        SHAPE,
        {lab: [(w, torch.tensor(m), torch.tensor(c)) for w, m, c in cs] for lab, cs in comps.items()},
        label_weights=pis,
    )
    # the numpy view: normalised weights; the unconditional branch is the π-weighted union
    norm = {lab: [(w / sum(x[0] for x in cs), m, c) for w, m, c in cs] for lab, cs in comps.items()}
    uncond = [(pis[lab] * w, m, c) for lab, cs in norm.items() for w, m, c in cs]
    return prior, norm, uncond


class TestGaussianMixturePrior:
    def test_smoke(self, mixture_setup):
        prior, _, _ = mixture_setup
        assert isinstance(prior, Prior)
        assert prior.vocabulary == ("left", "right")
        assert prior.sample_shape == SHAPE

    def test_eps_and_x0_match_numpy(self, mixture_setup):
        prior, norm, uncond = mixture_setup
        g = torch.Generator().manual_seed(0)
        z_t = torch.randn(6, *SHAPE, generator=g, dtype=torch.float64)
        t = torch.tensor([0, 20, 250, 500, 979, 999])
        labels = ["left", "right", "", "left", "", "right"]
        eps = prior.predict(z_t, t, Condition(labels), branches=("cond",)).eps["cond"]
        idx = prior.label_index(labels)
        x0 = prior.posterior(z_t, t, idx)[1]
        ab = ref.alpha_bar()[t.numpy()]
        rows = [uncond if lab == "" else norm[lab] for lab in labels]
        np.testing.assert_allclose(eps.numpy(), ref.batch_eps(z_t.numpy(), ab, rows), rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(x0.numpy(), ref.batch_x0(z_t.numpy(), ab, rows), rtol=1e-9, atol=1e-11)

    def test_unconditional_branch_is_label_marginal(self, mixture_setup):
        prior, _, uncond = mixture_setup
        z_t = torch.randn(3, *SHAPE, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        t = torch.tensor([100, 400, 800])
        e_u = prior.predict(z_t, t, Condition("left"), branches=("uncond",)).eps["uncond"]
        ab = ref.alpha_bar()[t.numpy()]
        np.testing.assert_allclose(e_u.numpy(), ref.batch_eps(z_t.numpy(), ab, [uncond] * 3), rtol=1e-9, atol=1e-11)

    def test_tweedie(self, mixture_setup):
        """ε̂ = −√(1 − ᾱ) ∇ log p_t(z_t), with p_t built by torch.distributions (independent of the code)."""
        prior, norm, _ = mixture_setup
        t = 300
        ab = float(ref.alpha_bar()[t])
        ws, mus, covs = zip(*norm["right"])
        mix = torch.distributions.Categorical(probs=torch.tensor(ws, dtype=torch.float64))
        comp = torch.distributions.MultivariateNormal(
            torch.tensor(np.stack(mus)) * ab**0.5,
            covariance_matrix=torch.tensor(np.stack([ab * ref.as_matrix(c, D) + (1 - ab) * np.eye(D) for c in covs])),
        )
        p_t = torch.distributions.MixtureSameFamily(mix, comp)
        z = torch.randn(4, D, generator=torch.Generator().manual_seed(2), dtype=torch.float64, requires_grad=True)
        (score,) = torch.autograd.grad(p_t.log_prob(z).sum(), z)
        eps = prior.predict(z.detach().reshape(4, *SHAPE), torch.full((4,), t), Condition("right"), ("cond",)).eps[
            "cond"
        ]
        torch.testing.assert_close(eps.reshape(4, D), -((1 - ab) ** 0.5) * score, rtol=1e-9, atol=1e-11)

    def test_means(self, mixture_setup):
        prior, norm, uncond = mixture_setup
        want_left = sum(w * m for w, m, _ in norm["left"])
        np.testing.assert_allclose(prior.mean("left").reshape(-1).numpy(), want_left, rtol=1e-12)
        np.testing.assert_allclose(prior.mean().reshape(-1).numpy(), sum(w * m for w, m, _ in uncond), rtol=1e-12)

    def test_dtype_follows_input_and_module_cast_keeps_precision(self, mixture_setup):
        prior, _, _ = mixture_setup
        z64 = torch.randn(2, *SHAPE, dtype=torch.float64)
        t = torch.tensor([10, 900])
        e64 = prior.predict(z64, t, Condition("left"), ("cond",)).eps["cond"]
        e32 = prior.to(torch.float32).predict(z64.float(), t, Condition("left"), ("cond",)).eps["cond"]
        assert e64.dtype == torch.float64 and e32.dtype == torch.float32
        torch.testing.assert_close(e32, e64.float(), rtol=1e-5, atol=1e-6)

    def test_outputs_are_usable_in_autograd(self, mixture_setup):
        """predict runs in inference mode but returns ordinary tensors (cloned), so a loss can mix them
        with tensors that require grad."""
        prior, _, _ = mixture_setup
        z = torch.randn(2, *SHAPE, requires_grad=True)
        eps = prior.predict(z, torch.tensor([5, 50]), Condition("left")).eps
        assert not eps["cond"].is_inference() and not eps["cond"].requires_grad
        (z * eps["cond"]).sum().backward()
        torch.testing.assert_close(z.grad, eps["cond"])

    def test_sample_moments(self):
        """Draws have the component's mean and (full) covariance, within CLT bounds."""
        rng = np.random.default_rng(7)
        mu, cov = rng.uniform(-0.5, 0.5, D), _spd(rng, 0.05, 0.3)
        prior = GaussianPrior(SHAPE, {"a": torch.tensor(mu)}, {"a": torch.tensor(cov)})
        n = 20000
        x = prior.sample(n, "a", torch.Generator().manual_seed(0), dtype=torch.float64).reshape(n, D).numpy()
        sd = np.sqrt(np.diag(cov))
        assert np.all(np.abs(x.mean(0) - mu) < 5 * sd / np.sqrt(n))
        emp = np.cov(x.T)
        # Var of a sample covariance entry is (Σ_ii Σ_jj + Σ_ij²)/n
        bound = 5 * np.sqrt((np.outer(np.diag(cov), np.diag(cov)) + cov**2) / n)
        assert np.all(np.abs(emp - cov) < bound)

    def test_unknown_label_lists_vocabulary(self, mixture_setup):
        prior, _, _ = mixture_setup
        with pytest.raises(ConditionError, match="unknown label 'top'; expected one of left, right"):
            prior.predict(torch.zeros(1, *SHAPE), torch.tensor([3]), Condition("top"))

    def test_shape_errors(self, mixture_setup):
        prior, _, _ = mixture_setup
        with pytest.raises(ConditionError, match=r"expected \(B, 3, 2, 2\)"):
            prior.predict(torch.zeros(1, 3, 4, 4), torch.tensor([3]), Condition("left"))
        with pytest.raises(ValueError, match="one timestep per sample"):
            prior.predict(torch.zeros(2, *SHAPE), torch.tensor([3]), Condition("left"))
        with pytest.raises(ConditionError, match="image has batch 3; expected 2"):
            prior.predict(
                torch.zeros(2, *SHAPE), torch.tensor([3, 4]), Condition("left", image=torch.zeros(3, 3, 2, 2))
            )

    @pytest.mark.parametrize(
        "components, match",
        [
            ({"a": [(0.0, torch.zeros(D), 1.0)]}, "weight must be a finite number > 0"),
            ({"a": [(1.0, torch.zeros(D + 1), 1.0)]}, "mean has 13 elements; expected 12"),
            ({"a": [(1.0, torch.zeros(D), -torch.ones(D))]}, "positive semi-definite"),
            ({"a": [(1.0, torch.zeros(D), torch.triu(torch.ones(D, D)))]}, "not symmetric"),
            ({"a": [(1.0, torch.zeros(D), torch.ones(5))]}, r"covariance has shape \(5,\)"),
            ({"a": []}, "at least one component"),
            ({"": [(1.0, torch.zeros(D), 1.0)]}, "non-empty strings"),
        ],
    )
    def test_invalid_parameters(self, components, match):
        with pytest.raises(ValueError, match=match):
            GaussianMixturePrior(SHAPE, components)

    def test_label_weights_must_cover_vocabulary(self):
        with pytest.raises(ValueError, match="must equal the vocabulary"):
            GaussianPrior(SHAPE, {"a": torch.zeros(D)}, {"a": 0.1}, label_weights={"b": 1.0})


class TestGaussianPrior:
    def test_single_gaussian_closed_form(self):
        """E[ε | z_t] = √(1−ᾱ) (ᾱΣ + (1−ᾱ)I)⁻¹ (z_t − √ᾱ μ), written out per dimension for diagonal Σ."""
        rng = np.random.default_rng(0)
        mu, var = rng.uniform(-0.5, 0.5, D), rng.uniform(0.01, 0.2, D)
        prior = GaussianPrior(SHAPE, {"a": torch.tensor(mu)}, {"a": torch.tensor(var)})
        z_t = rng.standard_normal((3, D))
        t = np.array([0, 500, 999])
        ab = ref.alpha_bar()[t][:, None]
        want = np.sqrt(1 - ab) * (z_t - np.sqrt(ab) * mu) / (ab * var + 1 - ab)
        got = prior.predict(torch.tensor(z_t).reshape(3, *SHAPE), torch.tensor(t), Condition("a"), ("cond",)).eps[
            "cond"
        ]
        np.testing.assert_allclose(got.reshape(3, D).numpy(), want, rtol=1e-12, atol=1e-14)

    def test_expected_x0_closed_form_and_monte_carlo(self):
        prior = GaussianPrior.random(("a",), SHAPE, seed=4, full=True)
        rng = np.random.default_rng(1)
        z = torch.tensor(rng.uniform(-1, 1, (1, D))).reshape(1, *SHAPE)
        t = 600
        got = prior.expected_x0(z, torch.tensor([t]), 0).reshape(D).numpy()
        m = prior.mixture(0)
        mu, cov = m.mu[0].numpy(), (m.basis[0] @ torch.diag(m.lam[0]) @ m.basis[0].T).numpy()
        ab = float(ref.alpha_bar()[t])
        np.testing.assert_allclose(
            got, ref.expected_x0_single(z.reshape(D).numpy(), ab, mu, cov), rtol=1e-10, atol=1e-12
        )
        # Monte Carlo over the forward noise, tolerance from the CLT
        n = 4000
        eps = torch.randn(n, *SHAPE, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
        z_t = ab**0.5 * z + (1 - ab) ** 0.5 * eps
        x0 = prior.posterior(z_t, torch.full((n,), t), 0)[1].reshape(n, D).numpy()
        assert np.all(np.abs(x0.mean(0) - got) < 5 * x0.std(0) / np.sqrt(n))

    def test_expected_x0_refuses_mixture(self):
        prior = GaussianPrior.random(("a", "b"), SHAPE)
        with pytest.raises(ConditionError, match="closed-form only for a one-component branch; this one has 2"):
            prior.expected_x0(torch.zeros(1, *SHAPE), torch.tensor([10]))  # unconditional = 2-label mixture

    def test_explicit_unconditional(self):
        prior = GaussianPrior.random(("a", "b"), SHAPE, unconditional=True)
        m = prior.mixture(2)
        assert m.num_components == 1
        assert torch.all(m.lam[0] > torch.maximum(prior.mixture(0).lam[0], prior.mixture(1).lam[0]))
        corr = ExpectedX0Corrective(prior)
        out = corr(torch.zeros(2, *SHAPE), torch.tensor([5, 900]))
        assert out.shape == (2, *SHAPE) and torch.isfinite(out).all()

    def test_corrective_cond_branch_needs_labels(self):
        prior = GaussianPrior.random(("a", "b"), SHAPE)
        corr = ExpectedX0Corrective(prior, branch="cond")
        with pytest.raises(ConditionError, match="needs the label_idx"):
            corr(torch.zeros(1, *SHAPE), torch.tensor([5]))
        out = corr(torch.zeros(2, *SHAPE), torch.tensor([5, 5]), label_idx=torch.tensor([0, 1]))
        assert not torch.allclose(out[0], out[1])

    @settings(max_examples=25, deadline=None)
    @given(a=st.floats(-2, 2), t=st.integers(0, 999), seed=st.integers(0, 2**16))
    def test_eps_is_affine_in_z_t(self, a, t, seed):
        """For one Gaussian, E[ε | z_t] is affine: ε(a z1 + (1−a) z2) = a ε(z1) + (1−a) ε(z2)."""
        prior = GaussianPrior.random(("a",), SHAPE, seed=1, full=True)
        g = torch.Generator().manual_seed(seed)
        z1, z2 = torch.randn(2, 1, *SHAPE, generator=g, dtype=torch.float64)
        tt = torch.tensor([t])

        def eps(z):
            return prior.predict(z, tt, Condition("a"), ("cond",)).eps["cond"]

        torch.testing.assert_close(eps(a * z1 + (1 - a) * z2), a * eps(z1) + (1 - a) * eps(z2), rtol=1e-9, atol=1e-9)


class TestRegistry:
    def test_builtins(self):
        assert get_prior("gaussian") is GaussianPrior
        assert get_prior("gaussian-mixture") is GaussianMixturePrior
        assert {"gaussian", "gaussian-mixture", "unet", "diffusers"} <= set(available_priors())

    def test_lazy_unet(self):
        from lasagna.priors.unet import UNetPrior

        assert get_prior("unet") is UNetPrior

    def test_duplicate_and_unknown(self):
        with pytest.raises(LasagnaError, match="'gaussian' is already registered"):
            register_prior("gaussian")(GaussianPrior)
        with pytest.raises(LasagnaError, match="'unet' is already registered"):
            register_prior("unet")(GaussianPrior)
        with pytest.raises(LasagnaError, match="unknown prior 'nope'; expected one of"):
            get_prior("nope")
        with pytest.raises(LasagnaError, match="expected a Prior subclass"):
            register_prior("not-a-prior")(int)
