"""The shared objective: views (area resize, crops), the conditioning image, loss construction, and
the gradient it sends into the layer — checked against the chain rule written out in numpy float64."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.distill import (
    ScoreObjective,
    Weights,
    build_loss,
    conditioning_image,
    crop,
    draw_patches,
    prior_image_size,
    resize,
)
from lasagna.distill.schedules import Ramp
from lasagna.errors import LasagnaError
from lasagna.generators import composite
from lasagna.losses import DDS, LMCSDS, SDS
from lasagna.priors import GaussianPrior
from lasagna.priors.unet import UNetConfig, UNetPrior

from .conftest import SHADING, gaussian_for


def unet_prior(cond_channels: int) -> UNetPrior:
    torch.manual_seed(0)
    return UNetPrior(UNetConfig(cond_channels=cond_channels, resolution=8, channels=(8, 16), vocabulary=("a",))).eval()


class TestViews:
    def test_area_resize_is_the_block_mean_float64(self):
        x = torch.rand(2, 3, 8, 12, dtype=torch.float64)
        ref = x.numpy().reshape(2, 3, 4, 2, 4, 3).mean(axis=(3, 5))
        np.testing.assert_allclose(resize(x, (4, 4)).numpy(), ref, rtol=1e-12)

    def test_resize_identity_and_upsampling(self):
        x = torch.rand(1, 3, 4, 4)
        assert resize(x, (4, 4)) is x
        up = resize(x, (8, 6))
        assert up.shape == (1, 3, 8, 6) and torch.isfinite(up).all()

    def test_patches_and_crops(self):
        g = torch.Generator().manual_seed(1)
        rows = draw_patches(3, (10, 7), (4, 4), 2, g)
        assert rows.shape == (6, 3) and rows[:, 0].tolist() == [0, 0, 1, 1, 2, 2]
        assert int(rows[:, 1].max()) <= 6 and int(rows[:, 2].max()) <= 3 and int(rows[:, 1:].min()) >= 0
        x = torch.arange(3 * 2 * 10 * 7, dtype=torch.float32).reshape(3, 2, 10, 7)
        out = crop(x, rows, (4, 4))
        for k, (s, t, left) in enumerate(rows.tolist()):
            assert torch.equal(out[k], x[s, :, t : t + 4, left : left + 4])
        assert torch.equal(draw_patches(3, (10, 7), (4, 4), 2, torch.Generator().manual_seed(1)), rows)

    def test_patch_larger_than_image(self):
        with pytest.raises(LasagnaError, match="do not fit"):
            draw_patches(1, (3, 8), (4, 4), 1, None)

    def test_prior_image_size(self):
        assert prior_image_size(gaussian_for(torch.rand(3, 4, 6))) == (4, 6)
        latent = gaussian_for(torch.rand(4, 2, 2))
        latent.vae_scale_factor = 8
        assert prior_image_size(latent) == (16, 16)


class TestConditioningImage:
    def test_follows_the_prior(self):
        base = torch.rand(2, 3, 8, 8, dtype=torch.float64)
        assert torch.equal(conditioning_image(unet_prior(3), base), base)
        assert conditioning_image(unet_prior(0), base) is None
        luma = conditioning_image(unet_prior(1), base)
        b = base.numpy()
        np.testing.assert_allclose(
            luma.numpy()[:, 0], 0.2126 * b[:, 0] + 0.7152 * b[:, 1] + 0.0722 * b[:, 2], rtol=1e-12
        )
        assert torch.equal(conditioning_image(gaussian_for(torch.rand(3, 4, 4)), base), base)  # no config: the RGB base

    def test_is_detached(self):
        base = torch.rand(1, 3, 4, 4, requires_grad=True)
        assert not conditioning_image(unet_prior(3), base).requires_grad


class TestBuildLoss:
    def test_names_and_interval(self):
        loss = build_loss("sds", t_min=0.1, t_max=0.5)
        assert isinstance(loss, SDS) and (loss.options.timesteps.t_min, loss.options.timesteps.t_max) == (0.1, 0.5)
        assert isinstance(build_loss("lmc-sds", corrective=lambda z, t, **k: z), LMCSDS)

    def test_lmc_needs_a_corrective(self):
        with pytest.raises(LasagnaError, match="corrective"):
            build_loss("lmc-sds")

    def test_interval_only_from_fields(self):
        with pytest.raises(LasagnaError, match="t_min/t_max"):
            build_loss("sds", options={"timesteps": {"t_min": 0.3}})

    def test_unknown(self):
        with pytest.raises(LasagnaError, match="unknown loss"):
            build_loss("magic")


class TestGradient:
    """d total / d y against the chain rule, for the whole view (area 2×2) and for the patch view."""

    @pytest.fixture()
    def setup(self):
        g = torch.Generator().manual_seed(5)
        base = (0.2 + 0.7 * torch.rand(2, 3, 8, 8, generator=g)).double()
        y = (0.5 + torch.rand(2, 1, 8, 8, generator=g)).double().requires_grad_()
        prior = gaussian_for(torch.rand(3, 4, 4, generator=g))
        weights = Weights(score=Ramp.constant(0.7), reg=Ramp.constant(0.3))
        return base, y, ScoreObjective(SHADING, prior, build_loss("sds"), 1.0, weights)

    def test_whole_view(self, setup):
        base, y, obj = setup
        out = obj(base, y, "x", rng=torch.Generator().manual_seed(0), step=0)
        out.total.backward()
        g = out.diagnostics.grad.numpy()  # (2, 3, 4, 4) the injected gradient in the prior's space
        b, yy = base.numpy(), y.detach().numpy()
        d_view = 0.7 * 2.0 * g / g.size  # score = surrogate / N; z = 2x − 1
        d_comp = np.repeat(np.repeat(d_view, 2, axis=2), 2, axis=3) / 4.0  # area 2×2: each pixel a quarter
        f = b * yy
        d_comp = d_comp + 0.3 * 2.0 * (f - b) / f.size
        ref = (d_comp * b).sum(axis=1, keepdims=True)  # multiply by a 1-channel y: Σ_c Cb_c
        np.testing.assert_allclose(y.grad.numpy(), ref, rtol=1e-9, atol=1e-15)
        assert out.w_score == 0.7 and out.w_reg == 0.3
        assert out.reg == pytest.approx(float(((f - b) ** 2).mean()), rel=1e-12)

    def test_patch_view_touches_only_the_patches(self, setup):
        base, y, obj = setup
        rows = torch.tensor([[0, 0, 0], [1, 4, 2]])
        out = obj(base, y, "x", rng=torch.Generator().manual_seed(0), step=0, patches=rows)
        out.total.backward()
        g = out.diagnostics.grad.numpy()
        grad = y.grad.numpy()
        inside = np.zeros_like(grad, dtype=bool)
        inside[0, :, 0:4, 0:4] = True
        inside[1, :, 4:8, 2:6] = True
        assert np.all(grad[~inside] == 0) and np.all(grad[inside] != 0)
        b, yy = base.numpy(), y.detach().numpy()
        bp, yp = b[1, :, 4:8, 2:6], yy[1, :, 4:8, 2:6]
        n_reg = 2 * 3 * 16
        ref = (0.7 * 2.0 * g[1] / g.size + 0.3 * 2.0 * (bp * yp - bp) / n_reg) * bp
        np.testing.assert_allclose(grad[1, :, 4:8, 2:6], ref.sum(axis=0, keepdims=True), rtol=1e-9)

    def test_schedule_enters_by_step(self):
        prior = gaussian_for(torch.rand(3, 4, 4))
        obj = ScoreObjective(SHADING, prior, build_loss("sds"), 1.0, Weights.lmc_network(10))
        base, y = torch.rand(1, 3, 4, 4), torch.ones(1, 1, 4, 4)
        first = obj(base, y, "x", rng=None, step=0)
        last = obj(base, y, "x", rng=None, step=10)
        assert (first.w_score, first.w_reg) == pytest.approx((0.1, 1.0)) and (
            last.w_score,
            last.w_reg,
        ) == pytest.approx((1.0, 0.1))

    def test_released_recipe_ends_without_the_l2(self):
        w = Weights.lmc_network(10, reg_end=0.0)
        assert w.at(0) == pytest.approx((0.1, 1.0)) and w.at(5) == pytest.approx((0.55, 0.5)) and w.at(10) == (1.0, 0.0)
        assert w.at(10_000) == (1.0, 0.0)

    def test_shape_errors(self):
        obj = ScoreObjective(SHADING, gaussian_for(torch.rand(3, 4, 4)), build_loss("sds"), 1.0, Weights())
        with pytest.raises(LasagnaError, match="layer has shape"):
            obj(torch.rand(1, 3, 4, 4), torch.ones(1, 1, 4, 5), "x", rng=None, step=0)
        with pytest.raises(LasagnaError, match="labels for a batch"):
            obj(torch.rand(2, 3, 4, 4), torch.ones(2, 1, 4, 4), ["x", "x", "x"], rng=None, step=0)


def test_dds_sees_the_identity_edit_as_its_source():
    """DDS's source is the base (the identity edit's composite): at the identity edit its gradient is 0."""
    prior = GaussianPrior.random(("x",), (3, 4, 4), seed=2)
    loss = build_loss("dds")
    obj = ScoreObjective(SHADING, prior, loss, 3.0, Weights())
    base = torch.rand(2, 3, 4, 4)
    y = SHADING.identity_layer(2, 4, 4)
    out = obj(base, y, "x", rng=torch.Generator().manual_seed(0), step=0)
    assert isinstance(loss, DDS) and torch.equal(loss.source_image, base)
    assert float(out.grad_norm.max()) < 1e-5
    assert torch.equal(composite(base, y, SHADING), base)
