"""The shared core: timestep sampling and annealing, w(t), CFG, gradient injection, the loss registry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from lasagna.errors import LasagnaError
from lasagna.losses import (
    SDS,
    ScoreLoss,
    TimestepOptions,
    TimestepSampler,
    available_losses,
    cfg,
    get_loss,
    inject,
    register_loss,
    weight,
)
from lasagna.priors import NoiseSchedule
from tests.losses import reference as ref


class TestTimestepSampler:
    def test_range_and_per_sample(self):
        s = TimestepSampler()
        t = s.sample(20000, NoiseSchedule(), torch.Generator().manual_seed(0))
        assert t.dtype == torch.long and t.shape == (20000,)
        assert int(t.min()) == 20 and int(t.max()) == 979  # round(0.02·999), round(0.98·999)
        assert len(t.unique()) > 900  # per sample, not one t for the batch

    def test_distribution_matches_rounding_cells(self):
        """Histogram vs the exact probabilities of round(u·999), u ~ U(0.02, 0.98) (chi-square-ish bound)."""
        n = 200_000
        t = TimestepSampler().sample(n, NoiseSchedule(), torch.Generator().manual_seed(1)).numpy()
        p = ref.timestep_probabilities()
        counts = np.bincount(t, minlength=1000)
        # group into 10 bins of 100 steps so every expected count is large
        exp, got = (p * n).reshape(10, 100).sum(1), counts.reshape(10, 100).sum(1)
        assert np.all(np.abs(got - exp) < 5 * np.sqrt(exp))

    def test_degenerate_range_is_constant(self):
        t = TimestepSampler(TimestepOptions(t_min=0.5, t_max=0.5)).sample(5, NoiseSchedule(), None)
        assert t.tolist() == [round(0.5 * 999)] * 5

    def test_seeded(self):
        a = TimestepSampler().sample(8, NoiseSchedule(), torch.Generator().manual_seed(3))
        b = TimestepSampler().sample(8, NoiseSchedule(), torch.Generator().manual_seed(3))
        assert torch.equal(a, b)

    @pytest.mark.parametrize("anneal", ["linear", "cosine"])
    def test_annealing(self, anneal):
        s = TimestepSampler(TimestepOptions(anneal=anneal, t_max_final=0.5, anneal_steps=100))
        assert s.t_max_at(0) == 0.98
        assert math.isclose(s.t_max_at(50), 0.74)  # both schedules pass the midpoint at half way
        assert s.t_max_at(100) == 0.5 and s.t_max_at(10_000) == 0.5
        quarter = 0.98 - 0.48 * (0.25 if anneal == "linear" else 0.5 * (1 - math.cos(math.pi / 4)))
        assert math.isclose(s.t_max_at(25), quarter)
        t = s.sample(1000, NoiseSchedule(), torch.Generator().manual_seed(0), step=100)
        assert int(t.max()) <= round(0.5 * 999)
        with pytest.raises(ValueError, match="pass step="):
            s.sample(2, NoiseSchedule(), None)

    @pytest.mark.parametrize(
        "kwargs, match",
        [
            ({"t_min": 0.9, "t_max": 0.1}, "must be <= t_max"),
            ({"anneal": "linear"}, "needs t_max_final"),
            ({"anneal": "cosine", "t_max_final": 0.01, "anneal_steps": 5}, r"must lie in \[t_min, t_max\]"),
            ({"t_max": 1.5}, "less than or equal to 1"),
            ({"bogus": 1}, "Extra inputs"),
        ],
    )
    def test_invalid_options(self, kwargs, match):
        with pytest.raises(ValidationError, match=match):
            TimestepOptions(**kwargs)


class TestWeightAndCFG:
    @pytest.mark.parametrize(
        "kind, fn",
        [
            ("uniform", lambda ab: np.ones_like(ab)),
            ("1-alpha_bar", lambda ab: 1 - ab),
            ("sqrt_alpha_bar(1-alpha_bar)", lambda ab: np.sqrt(ab) * (1 - ab)),
        ],
    )
    def test_weight_values(self, kind, fn):
        t = torch.tensor([0, 20, 500, 979, 999])
        got = weight(NoiseSchedule(), t, kind, torch.float64).numpy()
        np.testing.assert_allclose(got, fn(ref.alpha_bar()[t.numpy()]), rtol=1e-12)

    def test_unknown_weight(self):
        with pytest.raises(ValueError, match="unknown weighting 'snr'"):
            weight(NoiseSchedule(), torch.tensor([1]), "snr")  # type: ignore[arg-type]

    @settings(max_examples=30, deadline=None)
    @given(omega=st.floats(-5, 20), seed=st.integers(0, 1000))
    def test_cfg_convention(self, omega, seed):
        """ε_u + ω(ε_c − ε_u): ω = 0 → ε_u, ω = 1 → ε_c; the text-first form ε_c + s(ε_c − ε_u) is ω = s + 1."""
        g = torch.Generator().manual_seed(seed)
        e_u, e_c = torch.randn(2, 3, 4, generator=g, dtype=torch.float64)
        torch.testing.assert_close(cfg(e_u, e_c, omega), (1 - omega) * e_u + omega * e_c)
        torch.testing.assert_close(cfg(e_u, e_c, omega), e_c + (omega - 1) * (e_c - e_u))
        assert torch.equal(cfg(e_u, e_c, 0.0), e_u)


class TestInject:
    def test_derivative_is_exactly_grad(self):
        g = torch.Generator().manual_seed(0)
        z = torch.randn(4, 3, 8, 8, generator=g, requires_grad=True)
        grad = torch.randn(4, 3, 8, 8, generator=g) * 1e-3  # small g: the target trick would round here
        loss, diag = inject(z, grad)
        (dz,) = torch.autograd.grad(loss, z)
        assert torch.equal(dz, grad)
        # the value is ½‖g‖² (what 0.5‖z − sg(z − g)‖² evaluates to)
        assert math.isclose(float(loss.detach()), 0.5 * float((grad.double() ** 2).sum()), rel_tol=1e-4)
        np.testing.assert_allclose(diag.grad_norm.numpy(), grad.flatten(1).norm(dim=1).numpy(), rtol=1e-6)

    def test_target_trick_is_inexact_in_float32(self):
        """Why inject does not use ½‖z − sg(z − g)‖²: its float32 derivative is only z − (z − g) ≈ g."""
        z = torch.full((1000,), 3.0, requires_grad=True)
        grad = torch.full((1000,), 1e-4)
        loss = 0.5 * ((z - (z - grad).detach()) ** 2).sum()
        (dz,) = torch.autograd.grad(loss, z)
        assert not torch.equal(dz, grad)

    def test_non_finite_and_clamp(self):
        z = torch.zeros(2, 4, requires_grad=True)
        grad = torch.tensor([[1.0, float("nan"), -5.0, float("inf")], [0.5, -0.5, 2.0, float("-inf")]])
        loss, diag = inject(z, grad, clamp=1.0)
        (dz,) = torch.autograd.grad(loss, z)
        assert torch.equal(dz, torch.tensor([[1.0, 0.0, -1.0, 0.0], [0.5, -0.5, 1.0, 0.0]]))
        assert int(diag.non_finite) == 3 and int(diag.clamped) == 2
        assert torch.isfinite(loss)

    def test_errors(self):
        z = torch.zeros(2, 3)
        with pytest.raises(ValueError, match=r"expected z's shape \(2, 3\)"):
            inject(z, torch.zeros(3, 2))
        with pytest.raises(ValueError, match="clamp must be > 0"):
            inject(z, torch.zeros(2, 3), clamp=0.0)

    def test_same_value_and_derivative_as_target_trick_float64(self):
        """Same value and derivative as ½‖z − sg(z − g)‖² (DESIGN.md's convention), here in float64.
        (gradcheck does not apply: a stop-gradient surrogate's VALUE does not move with z.)"""
        g = torch.Generator().manual_seed(1)
        z = torch.randn(2, 5, generator=g, dtype=torch.float64, requires_grad=True)
        grad = torch.randn(2, 5, generator=g, dtype=torch.float64)
        trick = 0.5 * ((z - (z - grad).detach()) ** 2).sum()
        ours = inject(z, grad)[0]
        torch.testing.assert_close(ours, trick, rtol=1e-12, atol=0)
        torch.testing.assert_close(
            torch.autograd.grad(ours, z)[0], torch.autograd.grad(trick, z)[0], rtol=1e-12, atol=1e-15
        )

    @settings(max_examples=40, deadline=None)
    @given(
        scale=st.floats(1e-6, 1e6),
        shift=st.floats(-1e3, 1e3),
        seed=st.integers(0, 10_000),
    )
    def test_derivative_exact_property(self, scale, shift, seed):
        g = torch.Generator().manual_seed(seed)
        z = (torch.randn(3, 7, generator=g) + shift).requires_grad_(True)
        grad = torch.randn(3, 7, generator=g) * scale
        (dz,) = torch.autograd.grad(inject(z, grad)[0], z)
        assert torch.equal(dz, grad)


class TestRegistry:
    def test_builtins(self):
        assert set(available_losses()) >= {"sds", "lmc-sds", "dds", "nfsd", "ms-sds"}
        assert get_loss("sds") is SDS and SDS.name == "sds"

    def test_duplicate_and_unknown(self):
        with pytest.raises(LasagnaError, match="'sds' is already registered"):
            register_loss("sds")(SDS)
        with pytest.raises(LasagnaError, match="unknown loss 'vsd'; expected one of"):
            get_loss("vsd")
        with pytest.raises(LasagnaError, match="expected a ScoreLoss subclass"):
            register_loss("x")(dict)

    def test_options(self):
        assert SDS().options.weighting == "1-alpha_bar"
        assert SDS(weighting="uniform").options.weighting == "uniform"
        assert SDS({"clamp": 2.0}, weighting="uniform").options.clamp == 2.0
        assert SDS(SDS.Options(clamp=1.0), scale="inv_guidance").options.scale == "inv_guidance"
        with pytest.raises(ValidationError):
            SDS(weighting="snr")
        with pytest.raises(ValidationError):
            SDS(SDS.Options(), clamp=-1.0)  # overrides are validated too
        assert issubclass(SDS, ScoreLoss)
