"""LMC-SDS (Alldieck et al. 2024, eq. 6b, 9, 10) against numpy float64 re-derivations on Gaussian priors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.errors import LasagnaError
from lasagna.losses import LMCSDS, SDS, TimestepOptions, identity_corrective, normalize_like
from lasagna.numerics import STD_EPS
from lasagna.priors import Condition, ExpectedX0Corrective
from tests.losses import reference as ref
from tests.losses.conftest import SHAPE, components

B4 = (slice(None), None, None, None)


def _np_normalize(b: np.ndarray, zh: np.ndarray) -> np.ndarray:
    """eq. 10 per image: σ(ẑ)/σ(b̂)(b̂ − μ(b̂)) + μ(b̂), population std over (C, h, w)."""
    axes = (1, 2, 3)
    mb = b.mean(axes, keepdims=True)
    return zh.std(axes, keepdims=True) / b.std(axes, keepdims=True) * (b - mb) + mb


@pytest.mark.parametrize("fixed_eps", [False, True])
def test_terms_against_numpy(fixed_eps, gauss_params, prior_u):
    """grad = (1/ω)[ω(ε_c − ε_u)(z_t^c) + b̃ − ẑ_t(z_t^l)], every piece re-derived in float64."""
    omega, labels = 3.0, ["a", "b", "a", "b", "b"]
    image = torch.rand(5, *SHAPE, generator=torch.Generator().manual_seed(2))
    loss = LMCSDS(ExpectedX0Corrective(prior_u), fixed_eps=fixed_eps)
    d = loss(image, prior_u, Condition(labels), omega, rng=torch.Generator().manual_seed(3)).diagnostics
    t = d.t.numpy()
    ab = ref.alpha_bar()[t]
    sa, s1a = np.sqrt(ab)[B4], np.sqrt(1 - ab)[B4]
    z = 2 * image.double().numpy() - 1
    eps_c, eps_l = d.noise["cond"].double().numpy(), d.noise["lmc"].double().numpy()
    assert np.array_equal(eps_c, eps_l) != fixed_eps
    z_c, z_l = sa * z + s1a * eps_c, sa * z + s1a * eps_l
    unc = components(gauss_params, "", True)
    e_c = ref.batch_eps(z_c, ab, [components(gauss_params, lab, True) for lab in labels])
    e_u = ref.batch_eps(z_c, ab, [unc] * 5)
    z_hat = ref.batch_x0(z_l, ab, [unc] * 5)  # E[x | z_t^l], unconditional branch
    mu_u, var_u = gauss_params["u"]
    b_hat = np.stack([ref.expected_x0_single(z[i].reshape(-1), ab[i], mu_u, var_u) for i in range(5)]).reshape(z.shape)
    l_cond = omega * (e_c - e_u)
    l_lmc = _np_normalize(b_hat, z_hat) - z_hat
    np.testing.assert_allclose(d.components["cond"].numpy(), l_cond / omega, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(d.components["lmc"].numpy(), l_lmc / omega, rtol=1e-3, atol=1e-4)
    np.testing.assert_allclose(d.grad.numpy(), (l_cond + l_lmc) / omega, rtol=1e-3, atol=1e-4)


def _mean_lmc(prior, z: np.ndarray, n: int, corrective, normalize: str, u: float | None = None, seed: int = 0):
    """Sample mean and sd of n per-sample L_lmc terms at the clean image z (D,), ω = 1, scale none."""
    image = torch.tensor((z.reshape(1, *SHAPE) + 1) / 2, dtype=torch.float32).expand(n, *SHAPE)
    ts = TimestepOptions() if u is None else TimestepOptions(t_min=u, t_max=u)
    loss = LMCSDS(corrective, normalize=normalize, scale="none", timesteps=ts)
    d = loss(image, prior, Condition("a"), 1.0, rng=torch.Generator().manual_seed(seed)).diagnostics
    g = d.components["lmc"].double().reshape(n, -1).numpy()
    return g.mean(0), g.std(0), d


def test_exact_corrective_zeroes_expected_lmc_on_manifold(gauss_params, prior_u):
    """b̂ = E_ε[ẑ_t | z, t] (the perfectly trained corrective) ⇒ E_{t,ε}[L_lmc] = 0 on the data manifold
    (no eq.-10 normalisation). Power check: the trivial b̂ = z leaves a clearly non-zero mean."""
    n = 4000
    on_manifold = prior_u.sample(3, None, torch.Generator().manual_seed(9), dtype=torch.float64).reshape(3, -1).numpy()
    for z in on_manifold:
        mean, sd, _ = _mean_lmc(prior_u, z, n, ExpectedX0Corrective(prior_u), "none")
        assert np.all(np.abs(mean) < 5 * sd / np.sqrt(n))
    mean, sd, _ = _mean_lmc(prior_u, on_manifold[0], n, identity_corrective, "none")
    assert np.any(np.abs(mean) > 5 * sd / np.sqrt(n))


def test_exact_corrective_zeroes_expected_lmc_everywhere(gauss_params, prior_u):
    """For this b̂ the expectation vanishes off the manifold too (E ẑ_t is what b̂ IS): the manifold pull
    of LMC-SDS comes from b̂ NOT extrapolating like the denoiser, not from b̂'s accuracy on data."""
    n = 4000
    z = gauss_params["u"][0] + 1.5  # far outside the data (σ ≤ 0.55)
    mean, sd, _ = _mean_lmc(prior_u, z, n, ExpectedX0Corrective(prior_u), "none")
    assert np.all(np.abs(mean) < 5 * sd / np.sqrt(n))


def test_normalised_exact_corrective_leaves_contrast_term(gauss_params, prior_u):
    """With eq. 10, E[L_lmc] = (E σ(ẑ_t)/σ(b̂) − 1)(b̂ − μ(b̂)) at fixed t (b̂ = E ẑ_t): a pure contrast
    term with a positive coefficient, since E σ(ẑ) ≥ σ(E ẑ) (σ is convex)."""
    n, u = 4000, 0.2
    z = gauss_params["a"][0]
    mean, sd, d = _mean_lmc(prior_u, z, n, ExpectedX0Corrective(prior_u), "image", u=u)
    t = round(u * 999)
    ab = ref.alpha_bar()[t]
    mu_u, var_u = gauss_params["u"]
    b_hat = ref.expected_x0_single(z, ab, mu_u, var_u)
    z_l = np.sqrt(ab) * z + np.sqrt(1 - ab) * d.noise["lmc"].double().reshape(n, -1).numpy()
    z_hat = np.stack([ref.mixture_eps_x0(row, ab, [(1.0, mu_u, var_u)])[1] for row in z_l])
    coef = z_hat.std(1).mean() / b_hat.std() - 1
    assert coef > 0.1
    want = coef * (b_hat - b_hat.mean())
    bound = 5 * sd / np.sqrt(n)
    assert np.all(np.abs(mean - want) < bound)
    assert np.abs(want).max() > 3 * bound.max()  # the contrast term is really there


def test_fixed_eps_fixed_in_cond_resampled_in_lmc(gauss_params, prior_u):
    image = torch.rand(3, *SHAPE)
    loss = LMCSDS(ExpectedX0Corrective(prior_u), fixed_eps=True)
    d1 = loss(image, prior_u, Condition("a"), 2.0, rng=torch.Generator().manual_seed(1)).diagnostics
    d2 = loss(image, prior_u, Condition("a"), 2.0, rng=torch.Generator().manual_seed(2)).diagnostics
    assert torch.equal(d1.noise["cond"], d2.noise["cond"])
    assert not torch.allclose(d1.noise["lmc"], d2.noise["lmc"])
    # ... and the fixed ε is the one L_cond really used (numpy: ε_c − ε_u at √ᾱ z + √(1−ᾱ) ε_fixed)
    ab = ref.alpha_bar()[d2.t.numpy()]
    z = 2 * image.double().numpy() - 1
    z_c = np.sqrt(ab)[B4] * z + np.sqrt(1 - ab)[B4] * d1.noise["cond"].double().numpy()
    want = ref.batch_eps(z_c, ab, [components(gauss_params, "a", True)] * 3) - ref.batch_eps(
        z_c, ab, [components(gauss_params, "", True)] * 3
    )
    np.testing.assert_allclose(d2.components["cond"].numpy(), want, rtol=1e-4, atol=1e-5)  # ω·(…)/ω
    loss.reset_fixed_noise()  # the next call draws anew from ITS generator; same seed → same ε (reproducible)
    d3 = loss(image, prior_u, Condition("a"), 2.0, rng=torch.Generator().manual_seed(3)).diagnostics
    assert not torch.equal(d3.noise["cond"], d1.noise["cond"])
    d4 = loss(image, prior_u, Condition("a"), 2.0, rng=torch.Generator().manual_seed(1)).diagnostics
    assert torch.equal(d4.noise["cond"], d3.noise["cond"])
    # a seed makes the fixed ε the same across loss instances
    e = [
        LMCSDS(identity_corrective, fixed_eps=True, fixed_eps_seed=7)(
            image, prior_u, Condition("a"), 2.0, rng=torch.Generator().manual_seed(s)
        ).diagnostics.noise["cond"]
        for s in (0, 1)
    ]
    assert torch.equal(e[0], e[1])


def test_without_fixed_eps_one_noise(prior_u):
    d = LMCSDS(identity_corrective)(
        torch.rand(2, *SHAPE), prior_u, Condition("a"), 2.0, rng=torch.Generator().manual_seed(0)
    ).diagnostics
    assert torch.equal(d.noise["cond"], d.noise["lmc"])


def test_inverse_guidance_scaling(prior_u):
    image, corr = torch.rand(3, *SHAPE), ExpectedX0Corrective(prior_u)
    a = LMCSDS(corr, scale="none")(
        image, prior_u, Condition("b"), 5.0, rng=torch.Generator().manual_seed(4)
    ).diagnostics
    b = LMCSDS(corr)(image, prior_u, Condition("b"), 5.0, rng=torch.Generator().manual_seed(4)).diagnostics
    torch.testing.assert_close(b.grad, a.grad / 5.0)
    with pytest.raises(LasagnaError, match="ω must be > 0; got 0.0 \\(use scale='none'"):
        LMCSDS(corr)(image, prior_u, Condition("b"), 0.0, rng=None)
    with pytest.raises(LasagnaError, match="ω must be > 0; got -1.0"):
        LMCSDS(corr)(image, prior_u, Condition("b"), -1.0, rng=None)
    z = LMCSDS(corr, scale="none")(
        image, prior_u, Condition("b"), 0.0, rng=torch.Generator().manual_seed(4)
    ).diagnostics
    assert torch.count_nonzero(z.components["cond"]) == 0
    assert torch.equal(z.grad, z.components["lmc"])


def test_sqrt_snr_identity_is_sds_projection(prior_mix):
    """With b̂ = z, no normalisation and the √ᾱ/√(1−ᾱ) factor restored, L_lmc = L_proj (eq. 7)."""
    image = torch.rand(4, *SHAPE)
    lmc = LMCSDS(identity_corrective, normalize="none", lmc_weighting="sqrt_snr", scale="none")
    d_l = lmc(image, prior_mix, Condition("a"), 2.0, rng=torch.Generator().manual_seed(6)).diagnostics
    d_s = SDS(weighting="uniform")(
        image, prior_mix, Condition("a"), 2.0, rng=torch.Generator().manual_seed(6)
    ).diagnostics
    assert torch.equal(d_l.t, d_s.t)
    torch.testing.assert_close(d_l.components["lmc"], d_s.components["proj"], rtol=1e-3, atol=1e-4)
    torch.testing.assert_close(d_l.components["cond"], d_s.components["cond"])


def test_corrective_required_and_checked(prior_u):
    with pytest.raises(LasagnaError, match="no corrective b̂ given"):
        LMCSDS()
    with pytest.raises(LasagnaError, match="corrective must be callable"):
        LMCSDS(3)
    bad = LMCSDS(lambda z, t, cond_image=None, label_idx=None: z[:, :1])
    with pytest.raises(LasagnaError, match=r"corrective returned \(2, 1, 2, 2\); expected z's shape \(2, 3, 2, 2\)"):
        bad(torch.rand(2, *SHAPE), prior_u, Condition("a"), 1.0, rng=None)


def test_corrective_receives_documented_inputs(prior_u):
    seen = {}

    def spy(z, t, cond_image=None, label_idx=None):
        seen.update(z=z, t=t, cond_image=cond_image, label_idx=label_idx, grad=torch.is_grad_enabled())
        return z

    img, cimg = torch.rand(3, *SHAPE, requires_grad=True), torch.rand(3, *SHAPE)
    LMCSDS(spy)(img, prior_u, Condition(["a", "b", ""], image=cimg), 1.0, rng=torch.Generator().manual_seed(0))
    assert seen["t"].dtype == torch.long and seen["t"].shape == (3,)
    assert seen["label_idx"].tolist() == [0, 1, 2]  # "" is the null label
    assert seen["cond_image"] is cimg and not seen["grad"] and not seen["z"].requires_grad
    torch.testing.assert_close(seen["z"], 2 * img.detach() - 1)


class TestNormalisation:
    """eq. 10's b̃ as eq. 9 uses it (``normalize_like``) and as L_k trains b̂ (``corrective.lk_loss``)."""

    def test_reference_value(self):
        g = torch.Generator().manual_seed(0)
        zh, b = torch.randn(2, 2, 3, 4, 4, generator=g, dtype=torch.float64)
        np.testing.assert_allclose(normalize_like(b, zh).numpy(), _np_normalize(b.numpy(), zh.numpy()), rtol=1e-12)
        assert normalize_like(b, zh, "none") is b
        with pytest.raises(ValueError, match="unknown normalize 'channel'"):
            normalize_like(b, zh, "channel")  # type: ignore[arg-type]

    def test_same_as_the_correctives_training_normalisation(self):
        """L_lmc must apply b̂ exactly as L_k trained it (the paper: "the same operation in Eq. 9")."""
        corrective = pytest.importorskip("lasagna.losses.corrective")
        g = torch.Generator().manual_seed(1)
        zh, b = torch.randn(2, 3, 3, 4, 4, generator=g)
        torch.testing.assert_close(normalize_like(b, zh), corrective.rescale_to_target_std(b, zh))
        want = ((zh.double().numpy() - _np_normalize(b.double().numpy(), zh.double().numpy())) ** 2).mean()
        assert abs(float(corrective.lk_loss(b, zh)) - want) < 1e-5

    def test_sigma_zero_is_finite(self):
        """A constant b̂ (σ = 0), with a constant or random ẑ: finite b̃, finite L_k and finite gradient."""
        corrective = pytest.importorskip("lasagna.losses.corrective")
        b = torch.full((2, 3, 4, 4), 0.3, requires_grad=True)
        for zh in (torch.full((2, 3, 4, 4), -0.2), torch.randn(2, 3, 4, 4)):
            assert torch.isfinite(normalize_like(b, zh)).all()
            torch.testing.assert_close(normalize_like(b.detach(), zh), b.detach())  # (b̂ − μ(b̂)) = 0
            loss = corrective.lk_loss(b, zh)
            (gb,) = torch.autograd.grad(loss, b)
            assert torch.isfinite(loss) and torch.isfinite(gb).all()
        assert float(corrective.mean_std(torch.zeros(1, 3, 2, 2))[1]) == pytest.approx(STD_EPS)
        zb = torch.zeros(1, 3, 2, 2, requires_grad=True)
        (gz,) = torch.autograd.grad(corrective.mean_std(zb)[1].sum(), zb)
        assert torch.isfinite(gz).all()

    def test_gradcheck_float64(self):
        zh = torch.randn(2, 3, 2, 2, dtype=torch.float64)
        b = torch.randn(2, 3, 2, 2, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda x: normalize_like(x, zh), (b,))

    def test_half_precision_reduces_in_float32(self):
        zh, b = torch.randn(2, 3, 4, 4).bfloat16(), torch.randn(2, 3, 4, 4).bfloat16()
        out = normalize_like(b, zh)
        assert out.dtype == torch.bfloat16
        torch.testing.assert_close(out.float(), normalize_like(b.float(), zh.float()), rtol=2e-2, atol=2e-2)

    @settings(max_examples=30, deadline=None)
    @given(seed=st.integers(0, 10_000), a=st.floats(0.01, 100.0))
    def test_normalize_properties(self, seed, a):
        """b̃ keeps b̂'s mean, takes ẑ's σ, and is invariant to rescaling b̂'s centred part."""
        g = torch.Generator().manual_seed(seed)
        zh, b = torch.randn(2, 2, 3, 4, 4, generator=g, dtype=torch.float64)
        dims = (1, 2, 3)
        out = normalize_like(b, zh)
        torch.testing.assert_close(out.mean(dims), b.mean(dims))
        torch.testing.assert_close(out.std(dims, unbiased=False), zh.std(dims, unbiased=False))
        mb = b.mean(dims, keepdim=True)
        torch.testing.assert_close(normalize_like(a * (b - mb) + mb, zh), out)
