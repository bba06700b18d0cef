"""Properties every loss must have: shapes, mixed-condition batches, per-sample t, seeded
reproducibility, the surrogate's derivative, no gradient into the prior, and numerical stability."""

from __future__ import annotations

import math

import pytest
import torch

from lasagna.errors import ConditionError, LasagnaError
from lasagna.losses import DDS, LMCSDS, MSSDS, NFSD, SDS, TimestepOptions, identity_corrective
from lasagna.priors import Condition, ExpectedX0Corrective
from tests.losses.conftest import SHAPE, ConvPrior

NAMES = ["sds", "lmc-sds", "lmc-sds-fixed", "dds", "nfsd", "ms-sds"]


def make(name: str, prior=None, **opts):
    exact = (
        prior is not None
        and getattr(prior, "_uncond", None) is not None
        and prior.mixture(len(prior.vocabulary)).num_components == 1
    )
    corr = ExpectedX0Corrective(prior) if exact else identity_corrective
    return {
        "sds": lambda: SDS(**opts),
        "lmc-sds": lambda: LMCSDS(corr, **opts),
        "lmc-sds-fixed": lambda: LMCSDS(corr, fixed_eps=True, **opts),
        "dds": lambda: DDS(**opts),
        "nfsd": lambda: NFSD(**opts),
        "ms-sds": lambda: MSSDS(steps=3, **opts),
    }[name]()


def cond_for(b: int, image: torch.Tensor | None = None) -> Condition:
    labels = (["a", "b", ""] * b)[:b]  # a mixed batch, including unconditional samples
    src = torch.rand(b, *SHAPE, generator=torch.Generator().manual_seed(99)) if image is None else image
    return Condition(labels, image=src, negative=list(reversed(labels)))


@pytest.mark.parametrize("name", NAMES)
class TestEveryLoss:
    def test_shapes_and_per_sample_t(self, name, prior_u):
        b = 6
        image = torch.rand(b, *SHAPE, requires_grad=True)
        out = make(name, prior_u)(image, prior_u, cond_for(b), 2.0, rng=torch.Generator().manual_seed(0))
        d = out.diagnostics
        assert out.loss.shape == () and torch.isfinite(out.loss)
        assert d.grad.shape == (b, *SHAPE) and d.grad_norm.shape == (b,) and d.t.shape == (b,)
        assert len(set(d.t.tolist())) > 1
        assert all(c.shape == (b, *SHAPE) for c in d.components.values())
        torch.testing.assert_close(sum(d.components.values()), d.grad)  # the terms add up to the gradient
        s = d.summary()
        assert s["non_finite"] == 0 and math.isclose(s["grad_norm"], float(d.grad_norm.mean()))

    def test_derivative_wrt_composite(self, name, prior_u):
        image = torch.rand(3, *SHAPE, requires_grad=True)
        out = make(name, prior_u)(image, prior_u, cond_for(3), 2.0, rng=torch.Generator().manual_seed(1))
        (dimg,) = torch.autograd.grad(out.loss, image)
        assert torch.equal(dimg, 2 * out.diagnostics.grad)  # encode = 2x − 1

    def test_seeded_reproducibility(self, name, prior_u):
        image, cond = torch.rand(4, *SHAPE), cond_for(4)
        g = [
            make(name, prior_u)(image, prior_u, cond, 2.0, rng=torch.Generator().manual_seed(s)).diagnostics.grad
            for s in (5, 5, 6)
        ]
        assert torch.equal(g[0], g[1]) and not torch.equal(g[0], g[2])

    def test_no_gradient_into_prior_parameters(self, name):
        prior = ConvPrior()
        image = torch.rand(4, *SHAPE, requires_grad=True)
        out = make(name)(image, prior, cond_for(4), 2.0, rng=torch.Generator().manual_seed(2))
        out.loss.backward()
        assert image.grad is not None and torch.count_nonzero(image.grad) > 0
        assert all(p.grad is None for p in prior.parameters())
        assert all(p.requires_grad for p in prior.parameters())  # not because they were frozen

    def test_float64(self, name, prior_u):
        image = torch.rand(2, *SHAPE, dtype=torch.float64, requires_grad=True)
        cond = cond_for(2, image=torch.rand(2, *SHAPE, dtype=torch.float64))
        out = make(name, prior_u)(image, prior_u, cond, 2.0, rng=torch.Generator().manual_seed(0))
        assert out.diagnostics.grad.dtype == torch.float64
        out.loss.backward()
        assert image.grad.dtype == torch.float64


def _stability(name: str, prior, total: int) -> None:
    """``total`` per-sample evaluations in float32 over t ∈ {0.02, 0.98, U(0.02, 0.98)} and images
    {random, 0, 1, constant 0.5}: no NaN/inf anywhere (gradient, terms, surrogate)."""
    images = {
        "random": lambda n: torch.rand(n, *SHAPE, generator=torch.Generator().manual_seed(n)),
        "zeros": lambda n: torch.zeros(n, *SHAPE),
        "ones": lambda n: torch.ones(n, *SHAPE),
        "constant": lambda n: torch.full((n, *SHAPE), 0.5),
    }
    timesteps = [TimestepOptions(t_min=0.02, t_max=0.02), TimestepOptions(t_min=0.98, t_max=0.98), TimestepOptions()]
    per = math.ceil(total / (len(images) * len(timesteps)))
    gen, seen, ends = torch.Generator().manual_seed(0), 0, set()
    for ts in timesteps:
        loss = make(name, prior, timesteps=ts)
        for make_image in images.values():
            image = make_image(per).requires_grad_(True)
            out = loss(image, prior, cond_for(per), 7.5, rng=gen)
            d = out.diagnostics
            assert int(d.non_finite) == 0
            assert torch.isfinite(d.grad).all() and torch.isfinite(out.loss)
            assert all(torch.isfinite(c).all() for c in d.components.values())
            out.loss.backward()
            assert torch.isfinite(image.grad).all()
            seen += per
            ends.update(d.t.tolist())
    assert seen >= total and {20, 979} <= ends


@pytest.mark.parametrize("prior_name", ["prior_mix", "prior_u"])
@pytest.mark.parametrize("name", NAMES)
def test_stability_10k(name, prior_name, request):
    """The issue's 10 000 evaluations per loss, batched (well under a second per loss here); LMC-SDS
    runs with b̂ = z on the mixture prior (σ(b̂) = 0 on constant images) and the exact b̂ on the other."""
    _stability(name, request.getfixturevalue(prior_name), total=10_000)


def test_stability_network_prior_extreme_t():
    """A float32 network prior at the very ends of the schedule (t = 0 and T − 1, beyond the default range)."""
    prior = ConvPrior()
    for name in NAMES:
        for u in (0.0, 1.0):
            loss = make(name, timesteps=TimestepOptions(t_min=u, t_max=u))
            out = loss(torch.ones(4, *SHAPE), prior, cond_for(4), 7.5, rng=torch.Generator().manual_seed(0))
            assert int(out.diagnostics.non_finite) == 0 and torch.isfinite(out.loss)


class TestInputErrors:
    def test_image_checks(self, prior_u):
        loss = SDS()
        with pytest.raises(
            ConditionError, match=r"sds.image: expected the composite as a \(B, C, H, W\) tensor, got \(3, 2, 2\)"
        ):
            loss(torch.rand(*SHAPE), prior_u, Condition("a"), 1.0, rng=None)
        with pytest.raises(ConditionError, match=r"encodes to \(3, 4, 4\) but the prior works at \(3, 2, 2\)"):
            loss(torch.rand(1, 3, 4, 4), prior_u, Condition("a"), 1.0, rng=None)
        with pytest.raises(ConditionError, match="floating-point image"):
            loss(torch.ones(1, *SHAPE, dtype=torch.uint8), prior_u, Condition("a"), 1.0, rng=None)

    def test_labels_and_guidance(self, prior_u):
        loss = SDS()
        with pytest.raises(ConditionError, match="got 3 labels for a batch of 2"):
            loss(torch.rand(2, *SHAPE), prior_u, Condition(["a", "b", "a"]), 1.0, rng=None)
        with pytest.raises(ConditionError, match="unknown label 'c'; expected one of a, b"):
            loss(torch.rand(2, *SHAPE), prior_u, Condition("c"), 1.0, rng=None)
        with pytest.raises(LasagnaError, match="guidance must be finite"):
            loss(torch.rand(2, *SHAPE), prior_u, Condition("a"), float("nan"), rng=None)
        with pytest.raises(LasagnaError, match="guidance must be a number"):
            loss(torch.rand(2, *SHAPE), prior_u, Condition("a"), "high", rng=None)

    def test_annealing_needs_step(self, prior_u):
        loss = SDS(timesteps=TimestepOptions(anneal="linear", t_max_final=0.3, anneal_steps=10))
        with pytest.raises(ValueError, match="pass step="):
            loss(torch.rand(2, *SHAPE), prior_u, Condition("a"), 1.0, rng=None)
        d = loss(
            torch.rand(64, *SHAPE), prior_u, Condition("a"), 1.0, rng=torch.Generator().manual_seed(0), step=10
        ).diagnostics
        assert int(d.t.max()) <= round(0.3 * 999)

    def test_clamp_option(self, prior_u):
        d = SDS(clamp=1e-3)(
            torch.rand(2, *SHAPE), prior_u, Condition("a"), 7.5, rng=torch.Generator().manual_seed(0)
        ).diagnostics
        assert d.grad.abs().max() <= torch.tensor(1e-3) and int(d.clamped) > 0
