"""Noise-Free Score Distillation (Katzir et al. 2024, eq. 11) against numpy, with its per-sample t < 200 mask."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.errors import ConditionError
from lasagna.losses import NFSD, TimestepOptions
from lasagna.priors import Condition
from tests.losses import reference as ref
from tests.losses.conftest import SHAPE, components

B4 = (slice(None), None, None, None)


def test_against_numpy_with_mixed_regimes(gauss_params, prior_mix):
    """w(t)[ω(ε_c − ε_u) + δ_D], δ_D = ε_u if t < 200 else ε_u − ε_neg, per sample."""
    omega, n = 3.0, 16
    labels = ["a", "b"] * (n // 2)
    negs = ["b", "a"] * (n // 2)
    image = torch.rand(n, *SHAPE, generator=torch.Generator().manual_seed(0))
    d = NFSD()(
        image, prior_mix, Condition(labels, negative=negs), omega, rng=torch.Generator().manual_seed(4)
    ).diagnostics
    t = d.t.numpy()
    assert (t < 200).any() and (t >= 200).any()  # both regimes in one batch
    ab = ref.alpha_bar()[t]
    z_t = np.sqrt(ab)[B4] * (2 * image.double().numpy() - 1) + np.sqrt(1 - ab)[B4] * d.noise["eps"].double().numpy()
    e_c = ref.batch_eps(z_t, ab, [components(gauss_params, lab, False) for lab in labels])
    e_n = ref.batch_eps(z_t, ab, [components(gauss_params, lab, False) for lab in negs])
    e_u = ref.batch_eps(z_t, ab, [components(gauss_params, "", False)] * n)
    w = (1 - ab)[B4]
    delta_d = np.where((t < 200)[B4], e_u, e_u - e_n)
    np.testing.assert_allclose(d.components["cond"].numpy(), w * omega * (e_c - e_u), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(d.components["domain"].numpy(), w * delta_d, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(d.grad.numpy(), w * (omega * (e_c - e_u) + delta_d), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("index, small", [(199, True), (200, False)])
def test_threshold_is_t_200(index, small, prior_mix):
    image = torch.rand(2, *SHAPE)
    u = index / 999
    loss = NFSD(weighting="uniform", timesteps=TimestepOptions(t_min=u, t_max=u))
    d = loss(image, prior_mix, Condition("a", negative="b"), 1.0, rng=torch.Generator().manual_seed(0)).diagnostics
    assert d.t.tolist() == [index, index]
    e = prior_mix.predict_many(
        [(prior_mix.schedule.add_noise(2 * image - 1, d.noise["eps"], d.t), br) for br in ("uncond", "negative")],
        d.t,
        Condition("a", negative="b"),
    )
    want = e[0] if small else e[0] - e[1]
    torch.testing.assert_close(d.components["domain"], want)


def test_negative_from_options_and_errors(prior_mix):
    image = torch.rand(2, *SHAPE)
    a = NFSD(negative_label="b")(
        image, prior_mix, Condition("a"), 2.0, rng=torch.Generator().manual_seed(0)
    ).diagnostics
    b = NFSD()(image, prior_mix, Condition("a", negative="b"), 2.0, rng=torch.Generator().manual_seed(0)).diagnostics
    assert torch.equal(a.grad, b.grad)
    c = NFSD(negative_label="a")(
        image, prior_mix, Condition("a", negative="b"), 2.0, rng=torch.Generator().manual_seed(0)
    ).diagnostics
    assert torch.equal(c.grad, b.grad)  # condition.negative wins over the option
    with pytest.raises(ConditionError, match="NFSD needs a negative condition"):
        NFSD()(image, prior_mix, Condition("a"), 2.0, rng=None)
    with pytest.raises(ConditionError, match="unknown label 'dull'"):
        NFSD(negative_label="dull")(image, prior_mix, Condition("a"), 2.0, rng=None)
