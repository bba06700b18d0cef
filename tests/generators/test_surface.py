"""The surface estimator: flat at initialisation, any size, a unit source light, save/load round trip."""

from __future__ import annotations

import math

import pytest
import torch

from lasagna.compose.surface import MAX_FIT_ELEVATION, normals_from_height
from lasagna.document.condition import AMBIENT
from lasagna.errors import LasagnaError
from lasagna.generators.surface import SurfaceConfig, SurfaceEstimator

TOY = dict(channels=(4, 8), blocks=1, working_size=8)


@pytest.mark.parametrize("kind", ["albedo", "lit"])
def test_untrained_is_the_flat_surface(kind):
    net = SurfaceEstimator(SurfaceConfig(input=kind, **TOY))
    h = net(torch.rand(2, 3, 9, 13))  # not multiples of 2: padded and cropped back
    assert h.shape == (2, 1, 9, 13) and h.abs().max() == 0
    n = normals_from_height(h)
    assert torch.equal(n[:, 2], torch.ones_like(n[:, 2]))


def test_lit_estimates_its_source_shading_and_a_unit_light_facing_the_viewer():
    torch.manual_seed(0)
    net = SurfaceEstimator(SurfaceConfig(input="lit", **TOY))
    torch.nn.init.normal_(net.head.weight, std=3.0)  # extreme outputs: still a valid shading and light
    height, shading = net.decompose(torch.rand(5, 3, 8, 8))
    assert shading.min() >= 0.25 and shading.max() <= 1.0
    _, light = net.estimate(torch.rand(5, 3, 8, 8))
    torch.testing.assert_close(light.norm(dim=1), torch.ones(5), atol=1e-6, rtol=0)
    assert (light[:, 2] >= math.cos(math.radians(MAX_FIT_ELEVATION)) - 1e-6).all()
    _, none = SurfaceEstimator(SurfaceConfig(input="albedo", **TOY)).estimate(torch.rand(1, 3, 8, 8))
    assert none is None


def test_pixels_do_not_depend_on_the_batch():
    torch.manual_seed(1)
    net = SurfaceEstimator(SurfaceConfig(input="albedo", **TOY))
    torch.nn.init.normal_(net.head.weight)
    x = torch.rand(3, 3, 8, 8)
    whole = net(x)
    for i in range(3):
        torch.testing.assert_close(net(x[i : i + 1]), whole[i : i + 1], atol=1e-6, rtol=0)


def test_save_and_load(tmp_path):
    torch.manual_seed(2)
    net = SurfaceEstimator(SurfaceConfig(input="lit", **TOY))
    torch.nn.init.normal_(net.head.weight)
    net.save_pretrained(tmp_path / "s")
    back = SurfaceEstimator.from_pretrained(tmp_path / "s")
    x = torch.rand(1, 3, 8, 8)
    assert back.config == net.config
    assert torch.equal(back(x), net.eval()(x))


def test_bad_input():
    net = SurfaceEstimator(SurfaceConfig(input="albedo", **TOY))
    with pytest.raises(LasagnaError, match=r"image: image has shape \(1, 1, 8, 8\); expected \(B, 3, H, W\)"):
        net(torch.rand(1, 1, 8, 8))


@pytest.mark.parametrize("kind", ["albedo", "lit"])
def test_a_normals_head_starts_flat_and_always_faces_the_viewer(kind):
    net = SurfaceEstimator(SurfaceConfig(input=kind, output="normals", **TOY))
    n = net(torch.rand(2, 3, 9, 13))
    assert n.shape == (2, 3, 9, 13)
    torch.testing.assert_close(n, torch.tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1).expand_as(n), atol=1e-6, rtol=0)
    torch.manual_seed(3)
    torch.nn.init.normal_(net.head.weight, std=5.0)  # extreme outputs: still unit normals with n_z > 0
    n = net(torch.rand(4, 3, 8, 8))
    torch.testing.assert_close(n.norm(dim=1), torch.ones(4, 8, 8), atol=1e-5, rtol=0)
    assert n[:, 2].min() > 0
    torch.testing.assert_close(net.normals(n), n, atol=1e-6, rtol=0)  # already unit: unchanged


def test_estimate_at_enlarges_normals_to_unit_normals_facing_the_viewer():
    torch.manual_seed(4)
    net = SurfaceEstimator(SurfaceConfig(input="lit", output="normals", **TOY))
    torch.nn.init.normal_(net.head.weight, std=2.0)
    n, light = net.estimate_at(torch.rand(2, 3, 24, 40))
    assert n.shape == (2, 3, 24, 40) and light.shape == (2, 3)
    torch.testing.assert_close(n.norm(dim=1), torch.ones(2, 24, 40), atol=1e-5, rtol=0)
    assert n[:, 2].min() > 0


def test_estimate_at_another_working_size_reads_the_image_reduced_to_it():
    """``side`` overrides the size the estimator was trained at: the estimate is the one of the image reduced to
    that size (antialiased), enlarged back — the same numbers as doing those steps by hand."""
    from lasagna.compose.resample import downsample, working_size
    from lasagna.compose.surface import enlarge_surface

    torch.manual_seed(5)
    net = SurfaceEstimator(SurfaceConfig(input="lit", **TOY))
    torch.nn.init.normal_(net.head.weight, std=0.5)
    image = torch.rand(1, 3, 48, 32)
    own = net.config.working_size
    for side in (None, 12, 2 * own):
        n, light = net.estimate_at(image, side=side)
        small = downsample(image, working_size(48, 32, side or own))
        surface, expected_light = net.estimate(small)
        torch.testing.assert_close(n, net.normals(enlarge_surface(surface, (48, 32))))
        torch.testing.assert_close(light, expected_light)
    assert not torch.allclose(net.estimate_at(image, side=12)[0], net.estimate_at(image)[0], atol=1e-4)


def test_the_dome_prior_needs_a_silhouette_head_and_mixes_in_domes():
    from lasagna.generators.surface import DomePrior

    plain = SurfaceEstimator(SurfaceConfig(input="albedo", **TOY))
    with pytest.raises(LasagnaError, match="dome: this estimator has no silhouette head"):
        plain.estimate(torch.rand(1, 3, 8, 8), DomePrior(weight=0.5))
    assert plain.estimate(torch.rand(1, 3, 8, 8), DomePrior(weight=0.0))[0].shape == (1, 1, 8, 8)
    net = SurfaceEstimator(SurfaceConfig(input="lit", silhouette=True, **TOY))
    out = net.outputs(torch.rand(2, 3, 8, 8))
    assert out.silhouette.shape == (2, 1, 8, 8) and out.shading.shape == (2, 1, 8, 8)
    _, light = net.estimate(torch.rand(1, 3, 8, 8), DomePrior(weight=0.5, height=1.0))
    assert light.shape == (1, 3)
    # A disc of positive logits: the flat estimate mixed half and half with its dome.
    yy, xx = torch.meshgrid(torch.arange(15.0), torch.arange(15.0), indexing="ij")
    logit = 5.0 - ((yy - 7) ** 2 + (xx - 7) ** 2).sqrt()
    flat = torch.zeros(1, 3, 15, 15)
    flat[:, 2] = 1.0
    n = DomePrior(weight=0.5, height=1.0).apply(flat, logit[None, None])
    torch.testing.assert_close(n.norm(dim=1), torch.ones(1, 15, 15), atol=1e-6, rtol=0)
    assert n[0, 0, 7, 3] < -0.1 and n[0, 0, 7, 11] > 0.1  # the disc's left side leans left, its right side right
    assert n[0, 1, 3, 7] > 0.1 and n[0, 1, 11, 7] < -0.1  # its top leans up (+y), its bottom down
    assert torch.equal(n[0, :, 0, 0], torch.tensor([0.0, 0.0, 1.0]))  # outside: the estimate (flat)


def test_the_dome_prior_inflates_large_estimates_at_a_bounded_side():
    """A silhouette larger than ``DOME_MAX_SIDE`` is inflated reduced and its domes enlarged back: a disc still
    becomes the hemisphere (against the closed form, as closely as inflating it whole), with no distance matrix
    of the whole region."""
    from lasagna.compose.surface import DOME_MAX_SIDE, dome_normals, label_regions
    from lasagna.generators.surface import DomePrior

    side, radius = 2 * DOME_MAX_SIDE, 2 * DOME_MAX_SIDE / 3
    yy, xx = torch.meshgrid(torch.arange(float(side)), torch.arange(float(side)), indexing="ij")
    dx, dy = xx - (side - 1) / 2, (side - 1) / 2 - yy  # y up
    logit = (radius - (dx**2 + dy**2).sqrt())[None, None]
    sphere = torch.stack([dx / radius, dy / radius, (1 - (dx**2 + dy**2) / radius**2).clamp_min(0).sqrt()])[None]
    flat = torch.zeros(1, 3, side, side)
    flat[:, 2] = 1.0
    reduced = DomePrior(weight=1.0, height=1.0).apply(flat, logit)
    whole = dome_normals(label_regions(logit > 0), 1.0).float()
    core = (logit > radius / 4).expand(-1, 3, -1, -1)  # away from the outline, where the dome's slope is infinite
    err_reduced = float((reduced - sphere)[core].abs().mean())
    err_whole = float((whole - sphere)[core].abs().mean())
    assert err_reduced < 0.05 and err_reduced < 2 * err_whole + 0.01


def _mirrored(n: torch.Tensor, dims: tuple[int, ...], sign: tuple[float, float, float]) -> torch.Tensor:
    return (n.flip(dims) if dims else n) * torch.tensor(sign).view(1, 3, 1, 1)


def _transposed(n: torch.Tensor) -> torch.Tensor:
    """Normals of a surface transposed, by hand: h'(r, c) = h(c, r), so ∂h'/∂x = ∂h/∂row = −∂h/∂y and likewise."""
    t = n.transpose(-1, -2)
    return torch.stack([-t[:, 1], -t[:, 0], t[:, 2]], 1)


@pytest.mark.parametrize("kind", ["albedo", "lit"])
@pytest.mark.parametrize("symmetry", ["mirrors", "dihedral"])
def test_the_symmetry_ensemble_is_equivariant_and_averages_its_passes(kind, symmetry):
    """``symmetry``: the estimate of a mirrored (or, for 'dihedral', transposed) image is the mirrored (transposed)
    estimate — pixels moved, the normals' x or y negated (swapped and negated) — and the fitted light likewise,
    which one pass of a random convolutional estimator is not; and it is the renormalised mean of its passes'
    normals, mapped back by hand here."""
    from lasagna.compose.surface import facing_normals
    from lasagna.generators.surface import MIRRORS, DomePrior

    torch.manual_seed(6)
    net = SurfaceEstimator(SurfaceConfig(input=kind, silhouette=True, **TOY))
    torch.nn.init.normal_(net.head.weight, std=0.5)
    dome = DomePrior(weight=0.3, height=0.5)
    image = torch.rand(1, 3, 16, 12)
    n, light = net.estimate(image, dome, symmetry=symmetry)
    assert n.shape == (1, 3, 16, 12)
    torch.testing.assert_close(n.norm(dim=1), torch.ones(1, 16, 12), atol=1e-5, rtol=0)
    for dims, sign in MIRRORS[1:]:
        m, mirrored_light = net.estimate(image.flip(dims), dome, symmetry=symmetry)
        torch.testing.assert_close(m, _mirrored(n, dims, sign), atol=1e-5, rtol=0)
        one, _ = net.estimate(image.flip(dims), dome)
        assert not torch.allclose(one, _mirrored(n, dims, sign), atol=1e-3)  # one pass is not
        if kind == "lit":
            torch.testing.assert_close(mirrored_light, light * torch.tensor(sign), atol=1e-5, rtol=0)
        else:
            assert light is None and mirrored_light is None
    t, transposed_light = net.estimate(image.transpose(-1, -2), dome, symmetry=symmetry)
    assert torch.allclose(t, _transposed(n), atol=1e-5) == (symmetry == "dihedral")
    if kind == "lit" and symmetry == "dihedral":
        torch.testing.assert_close(transposed_light, torch.stack([-light[:, 1], -light[:, 0], light[:, 2]], 1))
    # By hand: each pass, mapped back, averaged and renormalised.
    passes = []
    for transpose in (False, True) if symmetry == "dihedral" else (False,):
        seen = image.transpose(-1, -2) if transpose else image
        for dims, sign in MIRRORS:
            one, _ = net.estimate(seen.flip(dims) if dims else seen, dome)
            one = _mirrored(one, dims, sign)
            passes.append(_transposed(one) if transpose else one)
    torch.testing.assert_close(n, facing_normals(torch.stack(passes).mean(0)), atol=1e-6, rtol=0)


def test_the_symmetry_ensemble_reaches_estimate_at_and_the_preset_field():
    from lasagna.catalogue import load_preset
    from lasagna.compose.resample import downsample
    from lasagna.compose.surface import enlarge_surface

    torch.manual_seed(7)
    net = SurfaceEstimator(SurfaceConfig(input="lit", **TOY))
    torch.nn.init.normal_(net.head.weight, std=0.5)
    image = torch.rand(1, 3, 32, 32)
    n, light = net.estimate_at(image, side=16, symmetry="dihedral")
    surface, expected = net.estimate(downsample(image, (16, 16)), symmetry="dihedral")
    torch.testing.assert_close(n, net.normals(enlarge_surface(surface, (32, 32))))
    torch.testing.assert_close(light, expected)
    with pytest.raises(LasagnaError, match="symmetry: got 'rotations'; expected one of none, mirrors, dihedral"):
        net.estimate(image, symmetry="rotations")
    # Chosen per preset on select (docs/BENCHMARKS.md, round 5): the relight's surface uses it, the shading's not.
    assert load_preset("relight").surface.symmetry == "dihedral" and load_preset("shading").surface.symmetry == "none"


@pytest.mark.parametrize("symmetry", ["none", "dihedral"])
def test_relief_deepens_the_estimate_and_the_light_is_fitted_to_the_deepened_surface(symmetry):
    """``relief`` g: the normals are the estimate's deepened by g (`deepen_normals`), and a lit estimate's source
    light is the fit of those normals to the same source shading (`fit_light`), not the undeepened surface's."""
    from lasagna.compose.surface import deepen_normals, fit_light

    torch.manual_seed(8)
    net = SurfaceEstimator(SurfaceConfig(input="lit", **TOY))
    torch.nn.init.normal_(net.head.weight, std=0.5)
    image = torch.rand(2, 3, 16, 16)
    flat_n, flat_light = net.estimate(image, symmetry=symmetry)
    deep_n, deep_light = net.estimate(image, symmetry=symmetry, relief=2.5)
    torch.testing.assert_close(deep_n, deepen_normals(net.normals(flat_n), 2.5), atol=1e-6, rtol=0)
    assert (deep_n[:, 2] < net.normals(flat_n)[:, 2] + 1e-6).all()  # steeper everywhere, never flatter
    shading = net.outputs(image).shading if symmetry == "none" else None
    if shading is not None:
        torch.testing.assert_close(deep_light, fit_light(deep_n, shading))
    assert not torch.allclose(deep_light, flat_light, atol=1e-4)
    same_n, same_light = net.estimate(image, symmetry=symmetry, relief=1.0)
    torch.testing.assert_close(same_n, flat_n, atol=0, rtol=0)
    n_at, light_at = net.estimate_at(image, side=16, symmetry=symmetry, relief=2.5)
    torch.testing.assert_close(n_at, deep_n, atol=1e-6, rtol=0)
    torch.testing.assert_close(light_at, deep_light)


@pytest.mark.parametrize("symmetry", ["none", "mirrors", "dihedral"])
def test_the_silhouette_is_the_heads_probability_averaged_over_the_ensemble(symmetry):
    """``silhouette``: the sigmoid of the silhouette head, in [0, 1], the mean of its passes mapped back (by hand
    here); under the ensemble a mirrored image gives the mirrored map; no head is a one-line refusal."""
    from lasagna.generators.surface import MIRRORS

    torch.manual_seed(9)
    net = SurfaceEstimator(SurfaceConfig(input="lit", silhouette=True, **TOY))
    torch.nn.init.normal_(net.head.weight, std=0.5)
    image = torch.rand(1, 3, 12, 12)
    p = net.silhouette(image, symmetry)
    assert p.shape == (1, 1, 12, 12) and float(p.min()) >= 0.0 and float(p.max()) <= 1.0
    passes = []
    for transpose in (False, True) if symmetry == "dihedral" else (False,):
        seen = image.transpose(-1, -2) if transpose else image
        for dims, _ in MIRRORS if symmetry != "none" else ((None, None),):
            one = torch.sigmoid(net.outputs(seen.flip(dims) if dims else seen).silhouette)
            one = one.flip(dims) if dims else one
            passes.append(one.transpose(-1, -2) if transpose else one)
    torch.testing.assert_close(p, torch.stack(passes).mean(0))
    if symmetry != "none":
        torch.testing.assert_close(net.silhouette(image.flip(-1), symmetry), p.flip(-1), atol=1e-6, rtol=0)
    plain = SurfaceEstimator(SurfaceConfig(input="lit", **TOY))
    with pytest.raises(LasagnaError, match="silhouette: this estimator has no silhouette head"):
        plain.silhouette(image)


def test_a_calibrated_elevation_maps_the_fitted_lights_elevation_and_keeps_its_azimuth():
    """``estimate(..., elevation=(offset, gain))``: the fitted light's elevation θ becomes offset + gain·θ (float64
    closed form), its azimuth and unit length kept, clamped at ``MAX_FIT_ELEVATION``; a light on the view axis keeps
    azimuth 0; (0, 1) is the identity."""
    from lasagna.compose.surface import calibrate_elevation

    torch.manual_seed(10)
    net = SurfaceEstimator(SurfaceConfig(input="lit", **TOY))
    torch.nn.init.normal_(net.head.weight, std=0.5)
    image = torch.rand(2, 3, 8, 8)
    _, light = net.estimate(image)
    _, moved = net.estimate(image, elevation=(26.43, 0.59))
    el = torch.rad2deg(torch.acos(light[:, 2].double()))
    want = (26.43 + 0.59 * el).clamp(0, MAX_FIT_ELEVATION)
    torch.testing.assert_close(torch.rad2deg(torch.acos(moved[:, 2].double())), want, atol=1e-3, rtol=0)
    torch.testing.assert_close(torch.atan2(moved[:, 1], moved[:, 0]), torch.atan2(light[:, 1], light[:, 0]))
    torch.testing.assert_close(moved.norm(dim=1), torch.ones(2), atol=1e-6, rtol=0)
    # float32 acos then cos near the view axis (θ of a few degrees): a few 1e-6 of round trip.
    torch.testing.assert_close(calibrate_elevation(light, 0.0, 1.0), light, atol=2e-5, rtol=0)
    up = torch.tensor([[0.0, 0.0, 1.0]])
    torch.testing.assert_close(calibrate_elevation(up, 30.0, 1.0), torch.tensor([[0.5, 0.0, math.sqrt(3) / 2]]))
    steep = calibrate_elevation(torch.tensor([[1.0, 0.0, 0.0]]), 0.0, 2.0)
    assert abs(math.degrees(math.acos(float(steep[0, 2]))) - MAX_FIT_ELEVATION) < 1e-4


def test_the_walls_elevation_lights_a_flat_wall_to_the_shadings_level_on_the_walls():
    """``estimate(..., source_elevation="walls")``: the source light's elevation is the one whose Lambert shading of
    a flat wall, a + (1 − a)·cos θ, equals the estimated source shading's mean over the walls weighted by
    1 − the silhouette probability (the ensemble's averages, by hand in float64); the azimuth is the fit's; an
    estimator without a silhouette head refuses in one line. `wall_elevation` against its closed form."""
    from lasagna.compose.surface import wall_elevation

    torch.manual_seed(11)
    net = SurfaceEstimator(SurfaceConfig(input="lit", silhouette=True, **TOY))
    torch.nn.init.normal_(net.head.weight, std=0.5)
    image = torch.rand(2, 3, 8, 8)
    _, fitted = net.estimate(image)
    _, light = net.estimate(image, source_elevation="walls")
    out = net.outputs(image)
    walls = 1.0 - torch.sigmoid(out.silhouette.double())
    level = (out.shading.double() * walls).sum((1, 2, 3)) / walls.sum((1, 2, 3))
    want = torch.rad2deg(torch.acos((level - AMBIENT) / (1 - AMBIENT)))
    torch.testing.assert_close(torch.rad2deg(torch.acos(light[:, 2].double())), want, atol=1e-3, rtol=0)
    torch.testing.assert_close(torch.atan2(light[:, 1], light[:, 0]), torch.atan2(fitted[:, 1], fitted[:, 0]))
    shading = torch.full((1, 1, 4, 4), AMBIENT + (1 - AMBIENT) * 0.5)  # a wall lit at 60°
    shading[..., :2, :] = 0.9  # an object, weighted out
    walls = torch.ones(1, 1, 4, 4)
    walls[..., :2, :] = 0.0
    got = wall_elevation(torch.tensor([[0.0, 1.0, 0.0]]), shading, walls)
    torch.testing.assert_close(got, torch.tensor([[0.0, math.sqrt(3) / 2, 0.5]]))
    plain = SurfaceEstimator(SurfaceConfig(input="lit", **TOY))
    with pytest.raises(LasagnaError, match="source_elevation: .*needs a silhouette head"):
        plain.estimate(image, source_elevation="walls")


def test_flat_walls_remove_the_walls_tilt_from_the_estimate_and_need_a_silhouette_head():
    """``estimate(..., flat_walls=s)`` is ``flatten_walls`` of the ensemble's normals with the walls weighted by
    1 − its silhouette probability and σ = s × the long side, applied before the relief gain and the light fit;
    an estimator without a silhouette head refuses in one line."""
    from lasagna.compose.surface import deepen_normals, flatten_walls

    torch.manual_seed(12)
    net = SurfaceEstimator(SurfaceConfig(input="lit", silhouette=True, **TOY))
    torch.nn.init.normal_(net.head.weight, std=0.5)
    image = torch.rand(1, 3, 16, 12)
    plain, _ = net.estimate(image, symmetry="mirrors")
    got, _ = net.estimate(image, symmetry="mirrors", flat_walls=0.25)
    walls = 1.0 - net.silhouette(image, "mirrors")
    want = flatten_walls(net.normals(plain), walls, 0.25 * 16)
    torch.testing.assert_close(got, want)
    assert float((got - net.normals(plain)).abs().max().detach()) > 1e-3  # the random net's walls did tilt
    deep, _ = net.estimate(image, symmetry="mirrors", flat_walls=0.25, relief=2.0)
    torch.testing.assert_close(deep, deepen_normals(want, 2.0))
    plain_net = SurfaceEstimator(SurfaceConfig(input="lit", **TOY))
    with pytest.raises(LasagnaError, match="flat_walls: .*silhouette head"):
        plain_net.estimate(image, flat_walls=0.25)


def test_a_wall_relief_gain_calms_the_walls_by_the_silhouette_and_needs_its_head():
    """``estimate(..., wall_relief=g)`` is ``calm_walls`` of the ensemble's normals with the walls weighted by
    1 − its silhouette probability, before the relief gain and the light fit (the fit is of the calmed normals);
    an estimator without a silhouette head refuses in one line."""
    from lasagna.compose.surface import calm_walls, deepen_normals, fit_light

    torch.manual_seed(13)
    net = SurfaceEstimator(SurfaceConfig(input="lit", silhouette=True, **TOY))
    torch.nn.init.normal_(net.head.weight, std=0.5)
    image = torch.rand(1, 3, 16, 12)
    plain, _ = net.estimate(image, symmetry="mirrors")
    walls = 1.0 - net.silhouette(image, "mirrors")
    got, light = net.estimate(image, symmetry="mirrors", wall_relief=0.25)
    want = calm_walls(net.normals(plain), walls, 0.25)
    torch.testing.assert_close(got, want)
    assert float((got - net.normals(plain)).abs().max().detach()) > 1e-3  # the random net's walls had relief
    _, shading, _ = net._views(image, None, "mirrors", None)
    torch.testing.assert_close(light, fit_light(want, shading))  # the light is fitted to the calmed normals
    deep, _ = net.estimate(image, symmetry="mirrors", wall_relief=0.25, relief=2.0)
    torch.testing.assert_close(deep, deepen_normals(want, 2.0))
    plain_net = SurfaceEstimator(SurfaceConfig(input="lit", **TOY))
    with pytest.raises(LasagnaError, match="wall_relief: .*silhouette head"):
        plain_net.estimate(image, wall_relief=0.5)


def _light_net(seed: int) -> SurfaceEstimator:
    """A toy lit estimator with a light input whose head and light channels are random (not the zero start)."""
    torch.manual_seed(seed)
    net = SurfaceEstimator(SurfaceConfig(input="lit", silhouette=True, light_input=True, **TOY))
    torch.nn.init.normal_(net.head.weight, std=0.5)
    return net


def test_a_light_input_needs_a_lit_estimator_and_a_light_row_per_image():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="a light input needs input 'lit'"):
        SurfaceConfig(input="albedo", light_input=True, **TOY)
    net = _light_net(0)
    with pytest.raises(LasagnaError, match=r"light has shape \(1, 3\); expected \(2, 3\)"):
        net.outputs(torch.rand(2, 3, 8, 8), torch.tensor([[0.0, 0.0, 1.0]]))
    plain = SurfaceEstimator(SurfaceConfig(input="lit", **TOY))
    with pytest.raises(LasagnaError, match="reads no light"):
        plain.outputs(torch.rand(1, 3, 8, 8), torch.tensor([[0.0, 0.0, 1.0]]))


def test_light_channels_are_the_light_and_a_given_flag_and_zero_when_not_known():
    from lasagna.generators.surface import LIGHT_CHANNELS, light_channels

    like = torch.zeros(3, 5, 4, 6, dtype=torch.float64)
    light = torch.tensor([[0.6, 0.0, 0.8], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    maps = light_channels(light, like)
    assert maps.shape == (3, LIGHT_CHANNELS, 4, 6) and maps.dtype == torch.float64
    expected = torch.tensor([[0.6, 0.0, 0.8, 1.0], [0.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(maps, expected[:, :, None, None].expand(3, 4, 4, 6), atol=1e-7, rtol=0)
    assert torch.equal(light_channels(None, like), torch.zeros(3, LIGHT_CHANNELS, 4, 6, dtype=torch.float64))


def test_the_light_changes_the_reading_and_an_unknown_light_is_read_twice():
    """A light input is read (two lights, two estimates); told nothing, the estimator reads the image alone, fits
    the light to that reading and reads the image again with it — reproduced here by hand."""
    from lasagna.compose.surface import fit_light

    net = _light_net(1)
    image = torch.rand(1, 3, 8, 8)
    left = net.estimate(image, light=torch.tensor([[-0.8, 0.0, 0.6]]))[0]
    right = net.estimate(image, light=torch.tensor([[0.8, 0.0, 0.6]]))[0]
    assert not torch.allclose(left, right, atol=1e-3)
    alone = net.outputs(image)  # None: the first reading (a zero light row)
    torch.testing.assert_close(alone.surface, net.outputs(image, torch.zeros(1, 3)).surface, atol=0, rtol=0)
    first_light = fit_light(net.normals(alone.surface), alone.shading)
    by_hand = net.estimate(image, light=first_light)
    auto = net.estimate(image)
    torch.testing.assert_close(auto[0], by_hand[0], atol=1e-6, rtol=0)
    torch.testing.assert_close(auto[1], by_hand[1], atol=1e-6, rtol=0)
    # readings=3: told the light fitted to the second reading; readings=1: the first reading alone.
    third = net.estimate(image, light=fit_light(net.normals(by_hand[0]), net.outputs(image, first_light).shading))
    torch.testing.assert_close(net.estimate(image, readings=3)[0], third[0], atol=1e-6, rtol=0)
    torch.testing.assert_close(net.estimate(image, readings=1)[0], alone.surface, atol=1e-6, rtol=0)
    with pytest.raises(LasagnaError, match="got 0; expected at least 1"):
        net.estimate(image, readings=0)


@pytest.mark.parametrize("symmetry", ["mirrors", "dihedral"])
def test_the_symmetry_ensemble_maps_a_given_light_into_each_view(symmetry):
    """With a light input, the ensemble stays equivariant when the light moves with the image: the estimate of the
    mirrored image under the mirrored light is the mirrored estimate (a light left in place would not give it)."""
    from lasagna.generators.surface import MIRRORS

    net = _light_net(2)
    image = torch.rand(1, 3, 12, 12)
    light = torch.nn.functional.normalize(torch.tensor([[0.5, 0.3, 0.8]]), dim=1)
    n, _ = net.estimate(image, symmetry=symmetry, light=light)
    for dims, sign in MIRRORS[1:]:
        mirrored_light = light * torch.tensor(sign)
        m, _ = net.estimate(image.flip(dims), symmetry=symmetry, light=mirrored_light)
        torch.testing.assert_close(m, _mirrored(n, dims, sign), atol=1e-5, rtol=0)
        stale, _ = net.estimate(image.flip(dims), symmetry=symmetry, light=light)
        assert not torch.allclose(stale, _mirrored(n, dims, sign), atol=1e-3)
    if symmetry == "dihedral":
        swapped = torch.stack([-light[:, 1], -light[:, 0], light[:, 2]], 1)
        t, _ = net.estimate(image.transpose(-1, -2), symmetry=symmetry, light=swapped)
        torch.testing.assert_close(t, _transposed(n), atol=1e-5, rtol=0)


@pytest.mark.parametrize("symmetry", ["none", "mirrors", "dihedral"])
def test_the_height_field_is_the_heads_heights_moved_back_averaged_and_centred(symmetry):
    """``height_field``: each pass's heights moved back as pixels (a height has no direction to turn), averaged and
    each image's mean removed (by hand here); the told light turned into each view as ``estimate`` turns it; under the
    ensemble a mirrored image, told the mirrored light, gives the mirrored field; a normals-output estimator is
    refused in one line."""
    from lasagna.generators.surface import MIRRORS, view_light

    torch.manual_seed(4)
    net = SurfaceEstimator(SurfaceConfig(input="lit", light_input=True, **TOY))
    torch.nn.init.normal_(net.head.weight, std=0.5)
    image = torch.rand(2, 3, 12, 12)
    light = torch.nn.functional.normalize(torch.tensor([[0.5, 0.3, 0.8], [-0.2, 0.6, 0.7]]), dim=1)
    h = net.height_field(image, symmetry, light)
    assert h.shape == (2, 1, 12, 12)
    passes = []
    for transpose in (False, True) if symmetry == "dihedral" else (False,):
        seen = image.transpose(-1, -2) if transpose else image
        for dims, sign in MIRRORS if symmetry != "none" else MIRRORS[:1]:
            one = net.outputs(seen.flip(dims) if dims else seen, view_light(light, dims, sign, transpose)).surface
            one = one.flip(dims) if dims else one
            passes.append(one.transpose(-1, -2) if transpose else one)
    want = torch.stack(passes).mean(0)
    torch.testing.assert_close(h, want - want.mean(dim=(-2, -1), keepdim=True), atol=1e-6, rtol=0)
    torch.testing.assert_close(h.mean(dim=(-2, -1)), torch.zeros(2, 1), atol=1e-6, rtol=0)
    if symmetry != "none":
        mirrored = net.height_field(image.flip(-1), symmetry, light * torch.tensor([-1.0, 1.0, 1.0]))
        torch.testing.assert_close(mirrored, h.flip(-1), atol=1e-5, rtol=0)
    normals = SurfaceEstimator(SurfaceConfig(input="lit", output="normals", **TOY))
    with pytest.raises(LasagnaError, match="height_field: this estimator outputs normals"):
        normals.height_field(image)
