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
    seen: list[int] = []
    a = distill_surface(base, prior, anchor=0.0, callback=lambda step, layer: seen.append(step), **kw)
    b = distill_surface(base, prior, anchor=0.0, **kw)
    assert seen == list(range(20))  # the editor's progress and cancel: once per step, before it
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


def test_a_relights_source_light_refined_with_the_surface_moves_toward_the_true_one():
    """A lit base A·S(n, l_src) and a prior whose label l has mean A·S(n, l) (the relit truth): from the true surface
    held by a strong anchor and a source light 25° off, stepping the light (``refine_source``) brings it closer; without
    it the light is returned as given."""
    truth = dome()
    n = normals_from_height(truth)
    true_src = light_vector(200.0, 30.0)[None]
    albedo = torch.full((1, 3, SIDE, SIDE), 0.7)
    base = albedo * lambert(n, true_src)
    prior = problem(albedo, truth)  # label l: A·S(n, l), what the relit composite base·S(l)/S(l_src) should be
    wrong = light_vector(200.0, 55.0)[None]
    kw = dict(init_surface=truth, lights=LIGHTS, steps=120, lights_per_step=4, lr=0.02, anchor=1e6, t_min=0.02)
    kw.update(t_max=0.5, seed=0, source=wrong)
    fit = distill_surface(base, prior, refine_source=True, **kw)
    kept = distill_surface(base, prior, **kw)

    def angle(a, b):
        return float(torch.rad2deg(torch.acos((a * b).sum().clamp(-1, 1))))

    assert angle(fit.source, true_src) < 0.5 * angle(wrong, true_src)
    assert torch.allclose(fit.source.norm(dim=-1), torch.ones(1), atol=1e-6)
    assert torch.allclose(kept.source, wrong)


def test_the_lock_removes_a_corrections_low_frequencies_and_keeps_its_detail():
    """``lock_sigma``: h₀ + (δ − G_σ∗δ). A constant correction is removed exactly (the mirrored, normalised Gaussian
    keeps a constant), a one-pixel checkerboard is kept to within its Gaussian's residue, and σ 0 is the identity."""
    from lasagna.distill.surface import _locked

    h0 = dome()
    board = ((torch.arange(SIDE)[:, None] + torch.arange(SIDE)[None]) % 2 * 2 - 1).float()[None, None] * 0.01
    assert torch.allclose(_locked(h0 + 0.3, h0, 0.2), h0, atol=1e-6)
    kept = _locked(h0 + board, h0, 0.2) - h0
    assert float((kept - board).abs().max()) < 0.1 * float(board.abs().max())
    assert torch.equal(_locked(h0 + board, h0, 0.0), h0 + board)


def test_the_smooth_band_removes_a_corrections_finest_relief_and_keeps_its_middle():
    """``smooth_sigma`` σ_f: h₀ + (G_f∗δ − G_σ∗δ). A one-pixel checkerboard (the finest relief a grid holds) is all
    but removed by σ_f 1 px; a correction of a middle wavelength (8 px) keeps most of its amplitude, against its
    closed-form Gaussian response exp(−2π²σ²/λ²); σ_f 0 keeps the board (the lock alone)."""
    import math

    from lasagna.distill.surface import _locked

    h0 = dome()
    board = ((torch.arange(SIDE)[:, None] + torch.arange(SIDE)[None]) % 2 * 2 - 1).float()[None, None] * 0.01
    assert float((_locked(h0 + board, h0, 0.0, None, 1.0) - h0).abs().max()) < 0.01 * float(board.abs().max())
    assert torch.allclose(_locked(h0 + board, h0, 0.0, None, 0.0), h0 + board)
    wave = (
        torch.cos(2 * math.pi * torch.arange(SIDE).float() / 8.0)[None, None, None, :].expand(1, 1, SIDE, SIDE) * 0.01
    )
    kept = (_locked(h0 + wave, h0, 0.0, None, 1.0) - h0)[..., SIDE // 2, SIDE // 4 : 3 * SIDE // 4]
    gain = math.exp(-2 * math.pi**2 / 8.0**2)  # a Gaussian of σ 1 px on a cosine of wavelength 8 px
    ref = wave[..., SIDE // 2, SIDE // 4 : 3 * SIDE // 4] * gain
    assert float((kept - ref).abs().max()) < 0.02 * 0.01  # the sampled kernel against the continuous response


def test_a_locked_refinement_keeps_the_starts_large_shape():
    """From a start that is the true dome plus a broad tilt, the locked refinement keeps the tilt (its correction has
    no low frequencies to undo it with), while the unlocked one is free to remove it."""
    from lasagna.compose.resample import gaussian_blur

    base = torch.full((1, 3, SIDE, SIDE), 0.8)
    truth = dome()
    prior = problem(base, truth)
    tilt = torch.linspace(-0.5, 0.5, SIDE)[None, None, None, :].expand_as(truth)
    start = truth + tilt
    kw = dict(init_surface=start, lights=LIGHTS, steps=150, lights_per_step=4, lr=0.02, anchor=0.0, t_min=0.02)
    kw.update(t_max=0.5, seed=0)
    free, locked = distill_surface(base, prior, **kw), distill_surface(base, prior, lock_sigma=0.3, **kw)
    sigma = 0.3 * SIDE
    broad = [float(gaussian_blur(fit.surface - start, sigma).abs().mean()) for fit in (free, locked)]
    assert broad[1] < 0.5 * broad[0]


def test_crops_at_native_resolution_after_the_whole_fraction():
    """``whole_fraction`` < 1 on a base larger than the prior: the later steps score crops of the prior's size (the
    result differs from scoring the whole image throughout, and repeats by seed); on a base of the prior's own size
    there is nothing to crop and the field changes nothing."""
    truth = dome()
    small = torch.full((1, 3, SIDE, SIDE), 0.8)
    prior = problem(small, truth)  # a prior of SIDE² images
    big = torch.nn.functional.interpolate(small, scale_factor=2, mode="nearest")
    start = torch.nn.functional.interpolate(0.5 * truth, scale_factor=2, mode="bicubic", align_corners=False)
    kw = dict(lights=LIGHTS, steps=12, lights_per_step=2, lr=0.02, anchor=0.0, seed=5)
    whole = distill_surface(big, prior, init_surface=start, **kw)
    crops = distill_surface(big, prior, init_surface=start, whole_fraction=0.5, **kw)
    again = distill_surface(big, prior, init_surface=start, whole_fraction=0.5, **kw)
    assert not torch.equal(whole.surface, crops.surface) and torch.equal(crops.surface, again.surface)
    same = [distill_surface(small, prior, init_surface=0.5 * truth, whole_fraction=f, **kw) for f in (1.0, 0.5)]
    assert torch.equal(same[0].surface, same[1].surface)
