"""Delta Denoising Score (Hertz et al. 2023) against numpy, and its zero when nothing is to be edited."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.errors import ConditionError
from lasagna.losses import DDS
from lasagna.priors import Condition
from tests.losses import reference as ref
from tests.losses.conftest import SHAPE, ConvPrior, components

B4 = (slice(None), None, None, None)


@pytest.mark.parametrize("prior_name", ["prior_mix", "prior_u"])
def test_zero_when_conditions_agree_and_source_is_image(prior_name, request):
    prior = request.getfixturevalue(prior_name)
    image = torch.rand(5, *SHAPE, generator=torch.Generator().manual_seed(0), requires_grad=True)
    labels = ["a", "b", "a", "b", "a"]
    out = DDS(source_image=image.detach())(
        image, prior, Condition(labels, negative=labels), 4.0, rng=torch.Generator().manual_seed(1)
    )
    assert torch.count_nonzero(out.diagnostics.grad) == 0
    assert torch.count_nonzero(out.diagnostics.components["target"]) > 0  # each SDS half is not zero
    out.loss.backward()
    assert torch.count_nonzero(image.grad) == 0


def test_zero_with_a_network_prior():
    """The same with a convolutional prior: the two halves of the batched pass see identical inputs."""
    prior = ConvPrior()
    image = torch.rand(4, *SHAPE)
    cond = Condition(["a", "b", "b", "a"], image=image, negative=["a", "b", "b", "a"])
    d = DDS()(image, prior, cond, 2.0, rng=torch.Generator().manual_seed(0)).diagnostics  # source = cond.image
    torch.testing.assert_close(d.grad, torch.zeros_like(d.grad), rtol=0, atol=1e-6)


def test_against_numpy(gauss_params, prior_mix):
    """∇ = ε̂^ω(z_t, y) − ε̂^ω(ẑ_t, ŷ), same ε and t, CFG on both (numpy float64)."""
    omega, labels, src_labels = 2.5, ["a", "b", "a"], ["b", "b", "a"]
    g = torch.Generator().manual_seed(3)
    image, source = torch.rand(2, 3, *SHAPE, generator=g)
    d = DDS(source_image=source)(image, prior_mix, Condition(labels, negative=src_labels), omega, rng=g).diagnostics
    ab = ref.alpha_bar()[d.t.numpy()]
    eps = d.noise["eps"].double().numpy()
    z, s = 2 * image.double().numpy() - 1, 2 * source.double().numpy() - 1
    z_t, s_t = np.sqrt(ab)[B4] * z + np.sqrt(1 - ab)[B4] * eps, np.sqrt(ab)[B4] * s + np.sqrt(1 - ab)[B4] * eps

    def guided(x_t, labs):
        e_c = ref.batch_eps(x_t, ab, [components(gauss_params, lab, False) for lab in labs])
        e_u = ref.batch_eps(x_t, ab, [components(gauss_params, "", False)] * 3)
        return e_u + omega * (e_c - e_u)

    want = guided(z_t, labels) - guided(s_t, src_labels)
    np.testing.assert_allclose(d.grad.numpy(), want, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(d.components["target"].numpy(), guided(z_t, labels) - eps, rtol=1e-4, atol=1e-5)
    assert np.abs(want).max() > 0.1


def test_source_broadcast_and_default(prior_mix):
    image = torch.rand(3, *SHAPE)
    src = torch.rand(1, *SHAPE)
    cond = Condition("a", negative="b")
    a = DDS(source_image=src)(image, prior_mix, cond, 1.0, rng=torch.Generator().manual_seed(0)).diagnostics
    b = DDS()(
        image,
        prior_mix,
        Condition("a", image=src.expand(3, *SHAPE), negative="b"),
        1.0,
        rng=torch.Generator().manual_seed(0),
    ).diagnostics
    assert torch.equal(a.grad, b.grad)  # a set source_image and the conditioning image agree
    loss = DDS()
    loss.source_image = src  # settable attribute
    c = loss(image, prior_mix, cond, 1.0, rng=torch.Generator().manual_seed(0)).diagnostics
    assert torch.equal(a.grad, c.grad)


def test_errors(prior_mix):
    image = torch.rand(2, *SHAPE)
    with pytest.raises(ConditionError, match="DDS needs the source condition"):
        DDS(source_image=image)(image, prior_mix, Condition("a"), 1.0, rng=None)
    with pytest.raises(ConditionError, match="DDS needs a source image"):
        DDS()(image, prior_mix, Condition("a", negative="a"), 1.0, rng=None)
    with pytest.raises(ConditionError, match=r"source image has shape \(3, 3, 2, 2\); expected \(1 or 2"):
        DDS(source_image=torch.rand(3, *SHAPE))(image, prior_mix, Condition("a", negative="a"), 1.0, rng=None)
    with pytest.raises(ConditionError, match="source image encodes to"):
        DDS(source_image=torch.rand(2, 3, 4, 4))(image, prior_mix, Condition("a", negative="a"), 1.0, rng=None)
