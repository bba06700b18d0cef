"""Multi-light score distillation of a surface against closed-form priors: the fixed point is the true surface's
shading under every light; determinism by seed; refusals."""

from __future__ import annotations

import pytest
import torch

from lasagna.compose.surface import inflate_regions, lambert, light_vector, normals_from_height
from lasagna.distill.surface import distill_surface
from lasagna.document.condition import parse_direction
from lasagna.errors import LasagnaError
from lasagna.priors import GaussianPrior

LIGHTS = ("left", "right", "top", "bottom")
SIDE = 12


def dome() -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.arange(SIDE), torch.arange(SIDE), indexing="ij")
    index = torch.where((yy - 5.5) ** 2 + (xx - 5.5) ** 2 < 4.5**2, 0, -1)[None, None]
    return inflate_regions(index).float()


def problem(base: torch.Tensor, height: torch.Tensor):
    """A Gaussian prior whose label l has mean base·S(n(h), l) (the composite of the true surface under l) and
    whose unconditional branch has their average: the SDS fixed point of every light is the true shading."""
    n = normals_from_height(height)
    images = {label: (base * lambert(n, light_vector(*parse_direction(label))[None]))[0] for label in LIGHTS}
    shape = tuple(base.shape[1:])
    flat = {lab: (img * 2 - 1).double().reshape(-1) for lab, img in images.items()}
    mean_all = torch.stack(list(flat.values())).mean(0)
    return GaussianPrior(shape, flat, {lab: 1e-3 for lab in LIGHTS}, unconditional=(mean_all, 1e-3))


def shading_error(height, truth) -> float:
    """Mean squared shading error over the four lights."""
    n, m = normals_from_height(height), normals_from_height(truth)
    lights = [light_vector(*parse_direction(lab))[None] for lab in LIGHTS]
    return float(sum((lambert(n, lv) - lambert(m, lv)).pow(2).mean() for lv in lights) / len(lights))


def test_multi_light_sds_moves_a_flat_surface_toward_the_true_one():
    base = torch.full((1, 3, SIDE, SIDE), 0.8)
    truth = dome()
    prior = problem(base, truth)
    flat = torch.zeros_like(truth)
    fit = distill_surface(
        base,
        prior,
        init_surface=flat,
        lights=LIGHTS,
        steps=150,
        lights_per_step=4,
        lr=0.02,
        anchor=0.0,
        t_min=0.02,
        t_max=0.5,
        seed=0,
    )
    assert shading_error(fit.surface, truth) < 0.5 * shading_error(flat, truth)
    assert len(fit.history) == 150 and fit.normals.shape == (1, 3, SIDE, SIDE)


def test_the_anchor_holds_the_start_and_the_seed_repeats():
    base = torch.full((1, 3, SIDE, SIDE), 0.8)
    truth = dome()
    prior = problem(base, truth)
    start = 0.5 * truth
    kw = dict(init_surface=start, lights=LIGHTS, steps=20, lights_per_step=2, lr=0.02, seed=3)
    held = distill_surface(base, prior, anchor=1e6, **kw)
    a, b = distill_surface(base, prior, anchor=0.0, **kw), distill_surface(base, prior, anchor=0.0, **kw)
    # Adam scales steps to about lr whatever the gradient: a strong anchor turns them back toward the start.
    assert float((held.surface - start).abs().max()) < 0.2 * float((a.surface - start).abs().max())
    assert torch.equal(a.surface, b.surface)


def test_refusals():
    base = torch.full((1, 3, SIDE, SIDE), 0.8)
    prior = problem(base, dome())
    with pytest.raises(LasagnaError, match=r"init_surface: init_surface has shape \(1, 1, 4, 4\)"):
        distill_surface(base, prior, init_surface=torch.zeros(1, 1, 4, 4), lights=LIGHTS)
    with pytest.raises(LasagnaError, match="expected at least one light"):
        distill_surface(base, prior, init_surface=torch.zeros(1, 1, SIDE, SIDE), lights=())
