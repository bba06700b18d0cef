"""Multi-step SDS (SparseFusion): K guided DDIM steps re-implemented in numpy; K = 1 is SDS."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.losses import MSSDS, SDS
from lasagna.priors import Condition
from tests.losses import reference as ref
from tests.losses.conftest import SHAPE, components


def test_one_step_is_sds(prior_mix):
    image = torch.rand(6, *SHAPE)
    cond = Condition(["a", "b", "a", "b", "a", "b"])
    a = MSSDS(steps=1)(image, prior_mix, cond, 3.0, rng=torch.Generator().manual_seed(2)).diagnostics
    b = SDS()(image, prior_mix, cond, 3.0, rng=torch.Generator().manual_seed(2)).diagnostics
    assert torch.equal(a.t, b.t)
    torch.testing.assert_close(a.grad, b.grad, rtol=1e-3, atol=1e-4)


@pytest.mark.parametrize("units", ["eps", "x0"])
def test_multistep_against_numpy(units, gauss_params, prior_mix):
    omega, steps, labels = 2.0, 3, ["a", "b", "b"]
    image = torch.rand(3, *SHAPE, generator=torch.Generator().manual_seed(1))
    d = MSSDS(steps=steps, units=units)(
        image, prior_mix, Condition(labels), omega, rng=torch.Generator().manual_seed(5)
    ).diagnostics
    abar = ref.alpha_bar()
    z0 = 2 * image.double().numpy() - 1
    eps = d.noise["eps"].double().numpy()
    want = []
    for i, t in enumerate(d.t.tolist()):
        cc, cu = components(gauss_params, labels[i], False), components(gauss_params, "", False)
        # DDIM (η = 0) from t through round(t (K − k)/K), k = 0..K−1; x̂₀ of the last evaluation
        ts = [int(np.round(t * (steps - k) / steps)) for k in range(steps + 1)]
        z = np.sqrt(abar[t]) * z0[i].ravel() + np.sqrt(1 - abar[t]) * eps[i].ravel()
        for k in range(steps):
            a = abar[ts[k]]
            e_c = ref.mixture_eps_x0(z, a, cc)[0]
            e_u = ref.mixture_eps_x0(z, a, cu)[0]
            e = e_u + omega * (e_c - e_u)
            x0 = (z - np.sqrt(1 - a) * e) / np.sqrt(a)
            if k + 1 < steps:
                z = np.sqrt(abar[ts[k + 1]]) * x0 + np.sqrt(1 - abar[ts[k + 1]]) * e
        g = (1 - abar[t]) * (z0[i].ravel() - x0)
        if units == "eps":
            g = g * np.sqrt(abar[t] / (1 - abar[t]))
        want.append(g.reshape(SHAPE))
    np.testing.assert_allclose(d.grad.numpy(), np.stack(want), rtol=1e-3, atol=1e-4)


def test_more_steps_change_the_gradient(prior_mix):
    image = torch.rand(2, *SHAPE)
    a = MSSDS(steps=1)(image, prior_mix, Condition("a"), 2.0, rng=torch.Generator().manual_seed(0)).diagnostics
    b = MSSDS(steps=8)(image, prior_mix, Condition("a"), 2.0, rng=torch.Generator().manual_seed(0)).diagnostics
    assert not torch.allclose(a.grad, b.grad, atol=1e-3)
