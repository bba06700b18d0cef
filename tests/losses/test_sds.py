"""SDS against closed forms on Gaussian priors (LMC-SDS eq. 3–6; DreamFusion eq. 3)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.losses import SDS, TimestepOptions
from lasagna.priors import Condition
from tests.losses import reference as ref
from tests.losses.conftest import SHAPE, components

W = {
    "uniform": lambda ab: np.ones_like(ab),
    "1-alpha_bar": lambda ab: 1 - ab,
    "sqrt_alpha_bar(1-alpha_bar)": lambda ab: np.sqrt(ab) * (1 - ab),
}


@pytest.mark.parametrize("weighting", list(W))
@pytest.mark.parametrize("explicit_uncond", [True, False])
def test_gradient_is_cond_plus_proj_against_numpy(weighting, explicit_uncond, gauss_params, prior_u, prior_mix):
    """∇ = w(t)[ω(ε_c − ε_u) + (ε_u − ε)] (eq. 6), each term re-derived in numpy float64 from the ε and
    t the loss reports; a batch of mixed labels with per-sample t."""
    prior = prior_u if explicit_uncond else prior_mix
    omega = 3.0
    labels = ["a", "b", "b", "a", "b", "a"]
    image = torch.rand(6, *SHAPE, generator=torch.Generator().manual_seed(0))
    out = SDS(weighting=weighting)(image, prior, Condition(labels), omega, rng=torch.Generator().manual_seed(1))
    d = out.diagnostics
    t, eps = d.t.numpy(), d.noise["eps"].double().numpy()
    assert len(set(t.tolist())) == 6  # per-sample timesteps
    ab = ref.alpha_bar()[t]
    z = 2 * image.double().numpy() - 1
    z_t = np.sqrt(ab)[:, None, None, None] * z + np.sqrt(1 - ab)[:, None, None, None] * eps
    e_c = ref.batch_eps(z_t, ab, [components(gauss_params, lab, explicit_uncond) for lab in labels])
    e_u = ref.batch_eps(z_t, ab, [components(gauss_params, "", explicit_uncond)] * 6)
    w = W[weighting](ab)[:, None, None, None]
    want_cond, want_proj = w * omega * (e_c - e_u), w * (e_u - eps)
    np.testing.assert_allclose(d.components["cond"].numpy(), want_cond, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(d.components["proj"].numpy(), want_proj, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(d.grad.numpy(), w * (e_u + omega * (e_c - e_u) - eps), rtol=1e-4, atol=1e-5)
    assert torch.equal(d.grad, d.components["cond"] + d.components["proj"])


@pytest.mark.parametrize("explicit_uncond", [True, False])
def test_guidance_one_is_one_conditional_pass_of_the_same_gradient(explicit_uncond, gauss_params, prior_u, prior_mix):
    """At ω = 1 the gradient is w(t)(ε_c − ε) against numpy float64 (the unconditional branch cancels in eq. 6),
    from one prior call of the conditional branch alone (half the batch of the ω ≠ 1 call); it equals the
    two-branch formula to rounding."""
    prior = prior_u if explicit_uncond else prior_mix
    labels = ["a", "b", "b", "a"]
    image = torch.rand(4, *SHAPE, generator=torch.Generator().manual_seed(2))
    calls = []
    real = prior.predict_many

    def spy(queries, t, cond):
        calls.append([br for _, br in queries])
        return real(queries, t, cond)

    prior.predict_many = spy
    try:
        d = SDS()(image, prior, Condition(labels), 1.0, rng=torch.Generator().manual_seed(3)).diagnostics
        two = SDS()(image, prior, Condition(labels), 1.0 + 1e-12, rng=torch.Generator().manual_seed(3)).diagnostics
    finally:
        del prior.predict_many
    assert calls == [["cond"], ["cond", "uncond"]]
    t, eps = d.t.numpy(), d.noise["eps"].double().numpy()
    ab = ref.alpha_bar()[t]
    z = 2 * image.double().numpy() - 1
    z_t = np.sqrt(ab)[:, None, None, None] * z + np.sqrt(1 - ab)[:, None, None, None] * eps
    e_c = ref.batch_eps(z_t, ab, [components(gauss_params, lab, explicit_uncond) for lab in labels])
    want = (1 - ab)[:, None, None, None] * (e_c - eps)
    np.testing.assert_allclose(d.grad.numpy(), want, rtol=1e-4, atol=1e-5)
    assert set(d.components) == {"guided"} and torch.equal(d.grad, d.components["guided"])
    torch.testing.assert_close(d.grad, two.grad, rtol=1e-5, atol=1e-6)


def test_derivative_wrt_composite(prior_u):
    """d(surrogate)/d(image) = Jᵀ_encode g = 2 g for a pixel prior (encode = 2x − 1), exactly."""
    image = torch.rand(4, *SHAPE, requires_grad=True)
    out = SDS()(image, prior_u, Condition("a"), 2.0, rng=torch.Generator().manual_seed(0))
    (dimg,) = torch.autograd.grad(out.loss, image)
    assert torch.equal(dimg, 2 * out.diagnostics.grad)


def test_inv_guidance_scale(prior_u):
    image = torch.rand(3, *SHAPE)
    a = SDS()(image, prior_u, Condition("a"), 4.0, rng=torch.Generator().manual_seed(5))
    b = SDS(scale="inv_guidance")(image, prior_u, Condition("a"), 4.0, rng=torch.Generator().manual_seed(5))
    torch.testing.assert_close(b.diagnostics.grad, a.diagnostics.grad / 4.0)


def _mean_gradient(
    prior, z: np.ndarray, label: str, omega: float, n: int, seed: int, **opts
) -> tuple[np.ndarray, np.ndarray]:
    """Sample mean and standard deviation of n per-sample SDS gradients at the clean image z (D,)."""
    image = torch.tensor((z.reshape(1, *SHAPE) + 1) / 2, dtype=torch.float32).expand(n, *SHAPE)
    g = SDS(**opts)(image, prior, Condition(label), omega, rng=torch.Generator().manual_seed(seed)).diagnostics.grad
    g = g.double().reshape(n, -1).numpy()
    return g.mean(0), g.std(0)


def test_expected_gradient_vanishes_at_conditional_mean(gauss_params, prior_mix):
    """ω = 1: E_{t,ε}[ε_c(z_t) − ε] = √(ᾱ(1−ᾱ)) C⁻¹(z − μ) = 0 at z = μ_c, for every t; checked by
    Monte Carlo with a CLT bound, and shown to have power by failing 0.15 away from the mean."""
    n = 4000
    mu = gauss_params["a"][0]
    mean, sd = _mean_gradient(prior_mix, mu, "a", 1.0, n, seed=0)
    assert np.all(np.abs(mean) < 5 * sd / np.sqrt(n))
    mean, sd = _mean_gradient(prior_mix, mu + 0.15, "a", 1.0, n, seed=0)
    assert np.any(np.abs(mean) > 5 * sd / np.sqrt(n))


@pytest.mark.parametrize("omega", [0.0, 2.5, 7.5])
def test_expected_gradient_vanishes_at_guided_fixed_point(omega, gauss_params, prior_u):
    """For ω ≠ 1 the zero of the expected gradient is the closed form z* of reference.sds_fixed_point."""
    n = 4000
    z_star, _ = ref.sds_fixed_point(omega, *gauss_params["a"], *gauss_params["u"])
    mean, sd = _mean_gradient(prior_u, z_star, "a", omega, n, seed=1)
    assert np.all(np.abs(mean) < 5 * sd / np.sqrt(n))


def _descend(prior, label: str, omega: float, steps: int, lr: float, n: int = 256, seed: int = 0) -> np.ndarray:
    """SGD on a free image with SDS; the Polyak average (second half) of z = 2x − 1."""
    x = torch.full((1, *SHAPE), 0.5, requires_grad=True)
    # ∂loss/∂x = 2 Σ_i g_i over n copies, and z = 2x − 1, so lr_x = lr/(4n) gives z ← z − lr·mean(g)
    opt = torch.optim.SGD([x], lr=lr / (4 * n))
    loss, gen = SDS(), torch.Generator().manual_seed(seed)
    tail = []
    for s in range(steps):
        opt.zero_grad()
        loss(x.expand(n, *SHAPE), prior, Condition(label), omega, rng=gen).loss.backward()
        opt.step()
        if s >= steps // 3:
            tail.append((2 * x.detach() - 1).double().reshape(-1).numpy())
    return np.mean(tail, axis=0)


@pytest.mark.parametrize("omega", [0.0, 1.0, 2.5, 7.5])
def test_descent_converges_to_closed_form_mode(omega, gauss_params, prior_u):
    """Gradient descent with SDS converges to z* = b/a (reference.sds_fixed_point: the t-averaged
    mode of p_c^ω p_u^(1−ω) for the default w(t) = 1 − ᾱ and t ~ U(0.02, 0.98)); for ω = 1 that is μ_c."""
    z_star, a = ref.sds_fixed_point(omega, *gauss_params["a"], *gauss_params["u"])
    got = _descend(prior_u, "a", omega, steps=300, lr=1.0 / a.max())
    np.testing.assert_allclose(got, z_star, atol=0.02)
    if omega == 1.0:
        np.testing.assert_allclose(z_star, gauss_params["a"][0], atol=1e-12)
    else:  # the test discriminates: the guided mode is far from the conditional mean
        assert np.abs(z_star - gauss_params["a"][0]).max() > 0.3


def test_descent_with_mixture_unconditional(gauss_params, prior_mix):
    """ω = 1 ignores the unconditional branch (here a 2-component mixture): the mode is μ_c."""
    _, a = ref.sds_fixed_point(1.0, *gauss_params["b"], *gauss_params["u"])
    got = _descend(prior_mix, "b", 1.0, steps=300, lr=1.0 / a.max())
    np.testing.assert_allclose(got, gauss_params["b"][0], atol=0.02)


def test_fixed_timestep_closed_form_expectation(gauss_params, prior_u):
    """At one fixed t the expected gradient is w √(ᾱ(1−ᾱ)) [ω(z−μ_c)/c_c + (1−ω)(z−μ_u)/c_u] (per dim)."""
    n, omega, u = 4000, 2.0, 0.5
    z = np.linspace(-0.8, 0.8, 12)
    mean, sd = _mean_gradient(prior_u, z, "a", omega, n, seed=3, timesteps=TimestepOptions(t_min=u, t_max=u))
    t = round(u * 999)
    ab = ref.alpha_bar()[t]
    (mu_c, var_c), (mu_u, var_u) = gauss_params["a"], gauss_params["u"]
    c_c, c_u = ab * var_c + 1 - ab, ab * var_u + 1 - ab
    want = (1 - ab) * np.sqrt(ab * (1 - ab)) * (omega * (z - mu_c) / c_c + (1 - omega) * (z - mu_u) / c_u)
    assert np.all(np.abs(mean - want) < 5 * sd / np.sqrt(n))
