"""Cast shadows over a height field (`lasagna.compose.shadow`) against numpy float64 ray marches
(tests/support/lights.py) and the closed form of a box's shadow."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lasagna.compose.shadow import directional_visibility, point_visibility, visibility
from lasagna.document.condition import unit_vector
from tests.support.lights import directional_shadow, point_shadow


def box(height: float = 0.2, size: int = 96) -> np.ndarray:
    """A flat map with one box 16 × 12 pixels, ``height`` canvas units tall."""
    h = np.zeros((size, size))
    h[40:56, 44:56] = height
    return h


def smooth_field(seed: int = 0, size: int = 80) -> np.ndarray:
    """A sum of Gaussian bumps (canvas units): smooth relief that casts shadows on itself at low lights."""
    rng = np.random.default_rng(seed)
    rows, cols = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    h = np.zeros((size, size))
    for _ in range(6):
        r, c, s, a = rng.uniform(10, size - 10), rng.uniform(10, size - 10), rng.uniform(3, 9), rng.uniform(0.1, 0.3)
        h += a * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * s * s))
    return h


def ours(h: np.ndarray, light) -> np.ndarray:
    t = torch.tensor(h, dtype=torch.float64)[None, None]
    if len(light) == 3 and isinstance(light[0], float) and abs(sum(c * c for c in light) - 1) < 1e-9:
        return directional_visibility(t, light)[0, 0].numpy()
    return point_visibility(t, light)[0, 0].numpy()


def near_an_edge(ref: np.ndarray, reach: int = 1) -> np.ndarray:
    """Pixels within ``reach`` pixels (a square) of a pixel of the reference's other kind (lit beside shadowed)."""
    shadowed = ref < 0.5
    pad = np.pad(shadowed, reach, mode="edge")
    h, w = shadowed.shape
    windows = [pad[i : i + h, j : j + w] for i in range(2 * reach + 1) for j in range(2 * reach + 1)]
    return np.any([win != shadowed for win in windows], axis=0)


def agreement(v: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(share of pixels where ours and the reference agree on lit or shadowed, share of the disagreeing pixels that
    lie within a pixel of the reference's shadow edge: tracing on a turned grid moves an edge by up to a pixel)."""
    wrong = (v < 0.5) != (ref < 0.5)
    if not wrong.any():
        return 1.0, 1.0
    return float(1 - wrong.mean()), float((wrong & near_an_edge(ref)).sum() / wrong.sum())


@pytest.mark.parametrize("field", ["box", "smooth"])
@pytest.mark.parametrize("az,el", [(0, 60), (135, 65), (250, 72), (300, 70)])
def test_a_directional_lights_shadows_match_a_ray_march(field, az, el):
    h = box() if field == "box" else smooth_field()
    ref = directional_shadow(h, unit_vector(az, el))
    assert (ref < 0.5).sum() > 40  # there is a shadow to find
    agree, at_edges = agreement(ours(h, unit_vector(az, el)), ref)
    assert agree >= 0.99 and at_edges >= 0.95, (agree, at_edges)


@pytest.mark.parametrize("el", [30.0, 45.0, 60.0, 70.0])
def test_a_boxs_shadow_is_as_long_as_its_height_over_the_rays_climb(el):
    """Lit from the left (az 180), a box of height H casts a shadow H·tan(el) canvas units long to its right (the
    light's elevation is from the view axis): within a pixel and a half, measured where the visibility crosses 1/2."""
    h = box(0.15)
    v = ours(h, unit_vector(180.0, el))
    row = v[48, 56:]  # the box's right edge is between columns 55 and 56 (bilinear: its top ends at 55.5)
    measured = float((row < 0.5).sum())
    expected = 0.15 * math.tan(math.radians(el)) * (96 / 2) - 0.5
    assert abs(measured - expected) <= 1.5, (measured, expected)
    assert (v[48, :44] > 0.5).all()  # nothing on the lit side


def test_a_point_lights_shadows_match_a_ray_march():
    """Over the map, near a corner and beyond it: the polar grid's running minimum against a march of each pixel's
    segment to the light."""
    cases = [(box(), (0.15, 0.2, 0.35)), (smooth_field(1), (0.8, 0.5, 0.2)), (box(0.3), (0.5, 0.5, 0.8))]
    cases += [(box(0.3), (2.5, -0.8, 1.0)), (smooth_field(3), (-0.6, 0.4, 0.3))]  # the light's foot beyond the map
    for h, point in cases:
        ref = point_shadow(h, *point)
        assert (ref < 0.5).sum() > 30
        agree, at_edges = agreement(ours(h, point), ref)
        assert agree >= 0.985 and at_edges >= 0.9, (agree, at_edges)


def test_nothing_is_shadowed_by_a_flat_map_a_frontal_light_or_a_lit_slope():
    flat = torch.zeros(1, 1, 40, 50)
    for text in ("left", "az=30,el=80", "x=0.1,y=0.9,z=0.05"):
        assert torch.equal(visibility(flat, text, (40, 50)), torch.ones(1, 1, 40, 50))
    bump = torch.tensor(smooth_field(2), dtype=torch.float32)[None, None]
    assert torch.equal(visibility(bump, "az=10,el=0", (80, 80)), torch.ones(1, 1, 80, 80))
    ramp = torch.linspace(0, 0.5, 64).view(1, 1, 1, 64).expand(1, 1, 32, 64).contiguous()  # rises toward +x
    assert visibility(ramp, "az=0,el=75", (32, 64)).min() == 1.0  # the light climbs faster than the ramp: lit
    assert visibility(ramp, "az=180,el=75", (32, 64)).max() == 1.0  # lit from behind the ramp: self-facing away only


def test_visibility_is_traced_small_and_enlarged_to_the_layer():
    h = torch.tensor(box(), dtype=torch.float32)[None, None]
    v = visibility(h, "az=0,el=60", (192, 192))
    assert v.shape == (1, 1, 192, 192) and 0.0 <= float(v.min()) and float(v.max()) <= 1.0
    small = visibility(h, "az=0,el=60", (96, 96))
    assert torch.allclose(torch.nn.functional.avg_pool2d(v, 2), small, atol=0.26)


def test_ambient_occlusion_is_the_share_of_a_cosine_weighted_sky_each_point_sees():
    """Against a numpy float64 mean of ray marches over the same directions (tests/support/lights.py): within 0.04
    everywhere but a pixel from an edge; a flat map sees all the sky (exactly 1); beside a tall wall a point sees half
    of it; the top of the wall all of it."""
    from lasagna.compose.shadow import occlusion
    from tests.support.lights import sky_share

    h = smooth_field(4, 48)
    ours_ = occlusion(torch.tensor(h)[None, None], (48, 48))[0, 0].numpy()
    ref = sky_share(h)
    inner = np.zeros_like(h, dtype=bool)
    inner[2:-2, 2:-2] = True
    assert np.abs(ours_ - ref)[inner].mean() <= 0.02 and np.abs(ours_ - ref)[inner].max() <= 0.2
    assert ref.min() < 0.8  # the bumps hide some sky
    assert torch.equal(occlusion(torch.zeros(1, 1, 20, 30), (20, 30)), torch.ones(1, 1, 20, 30))
    wall = torch.zeros(1, 1, 40, 40, dtype=torch.float64)
    wall[..., 20:] = 5.0  # a wall 5 canvas units tall along the map's middle
    seen = occlusion(wall, (40, 40))[0, 0]
    assert ((seen[12:28, 18:20] - 0.5).abs() <= 0.05).all(), seen[12:28, 18:20]  # at its foot
    assert (seen[10:30, 22:38] >= 0.99).all()
