"""Wall relief: closed-form gradients against finite differences of the height field (numpy float64),
and the rendered wall's shading against Lambert on those normals."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lasagna.world import render, sample_scenes
from lasagna.world.lighting import AMBIENT, LIGHTS
from lasagna.world.relief import N_RELIEF_PARAMS, RELIEF_DRAWS, RELIEF_NAMES, RELIEFS, relief_normals
from tests.world.helpers import pixel_centres


def height(name: str, x: np.ndarray, y: np.ndarray, prm: np.ndarray) -> np.ndarray:
    """The height fields of `lasagna.world.relief`'s docstring, written out independently."""
    if name == "bumps":
        h = np.zeros_like(x)
        for i in range(5):
            cx, cy, sigma, amp = prm[4 * i : 4 * i + 4]
            h += amp * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sigma**2))
        return h
    if name == "grooves":
        phi, period, width, depth, offset = prm[:5]
        xi = np.mod(np.cos(phi) * x + np.sin(phi) * y + offset, period) / (width * period)
        return np.where(xi < 1, -depth * np.sin(np.pi * xi) ** 2, 0.0)
    if name == "bevels":
        h = np.zeros_like(x)
        for i in range(2):
            cx, cy, hx, hy, rim, slope = prm[6 * i : 6 * i + 6]
            e = np.minimum(hx - np.abs(x - cx), hy - np.abs(y - cy))
            h += slope * np.clip(e, 0.0, rim)
        return h
    if name == "ripples":
        cx, cy, wavelength, amp, reach = prm[:5]
        r = np.hypot(x - cx, y - cy)
        return np.where(r < reach, amp * np.sin(2 * np.pi * r / wavelength), 0.0)
    raise AssertionError(name)


def sample(name: str, seed: int) -> np.ndarray:
    return RELIEFS[name].sample(np.random.default_rng(seed).random(RELIEF_DRAWS))


def fd_gradient(name, x, y, prm, h=1e-6):
    gx = (height(name, x + h, y, prm) - height(name, x - h, y, prm)) / (2 * h)
    gy = (height(name, x, y + h, prm) - height(name, x, y - h, prm)) / (2 * h)
    return gx, gy


def away_from_kinks(name, x, y, prm, fine) -> np.ndarray:
    """Points where differences of step 1e-6 (``fine``) and 1e-4 agree: no kink within 1e-4."""
    cx, cy = fd_gradient(name, x, y, prm, 1e-4)
    return (np.abs(fine[0] - cx) < 1e-5) & (np.abs(fine[1] - cy) < 1e-5)


@pytest.mark.parametrize("name", RELIEF_NAMES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradient_matches_finite_differences(name, seed):
    prm = sample(name, seed)
    assert prm.shape == (N_RELIEF_PARAMS,)
    rng = np.random.default_rng(100 + seed)
    x, y = rng.uniform(-1, 1, 4000), rng.uniform(-1, 1, 4000)
    gx, gy = RELIEFS[name].gradient(torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(prm).expand(4000, -1))
    fx, fy = fd_gradient(name, x, y, prm)
    # Grooves, bevels and ripples have kinks (the groove's ends, the rim's edges, the ripples' centre and
    # reach): there the two one-sided
    # slopes differ and a central difference straddles them. Away from kinks they must agree.
    smooth = away_from_kinks(name, x, y, prm, (fx, fy))
    assert smooth.mean() > 0.9
    np.testing.assert_allclose(gx.numpy()[smooth], fx[smooth], atol=1e-5)
    np.testing.assert_allclose(gy.numpy()[smooth], fy[smooth], atol=1e-5)
    # Each component's steepest slope is at most 1.2; overlapping bumps or bevels add up.
    slope = np.hypot(gx.numpy(), gy.numpy())
    components = {"bumps": 5, "grooves": 1, "bevels": 2, "ripples": 1}[name]
    assert slope.max() <= 1.2 * components * (1 + 1e-9) and slope.max() > 0.05


def test_normals_are_unit_and_flat_where_no_relief():
    prm = torch.from_numpy(np.stack([sample("bumps", 0), sample("grooves", 0), sample("bevels", 0)]))
    kind = torch.tensor([0, 1, 2, -1]).repeat_interleave(50)
    x = torch.linspace(-1, 1, 200, dtype=torch.float64)
    n = relief_normals(kind, torch.cat([prm, prm[:1]]).repeat_interleave(50, 0), x, -x)
    norm = torch.sqrt(n[0] ** 2 + n[1] ** 2 + n[2] ** 2)
    torch.testing.assert_close(norm, torch.ones_like(norm), atol=1e-12, rtol=0)
    assert (n[2] > 0).all() and (n[0][150:] == 0).all() and (n[2][150:] == 1).all()


@pytest.mark.parametrize("label", ["left", "top-right"])
def test_rendered_wall_is_lambert_on_the_relief(label):
    p = sample_scenes("train", 0, range(40))
    rough = (p.relief >= 0).nonzero().squeeze(1)[:4]
    assert len(rough) == 4
    p = p.select(rough)
    p = type(p)(**{**p.__dict__, "present": torch.zeros_like(p.present)}).with_labels(label)
    s = render(p, 48, dtype=torch.float64)
    x, y = pixel_centres(48)
    lx, ly, lz = LIGHTS[label]
    for b in range(len(rough)):
        name = RELIEF_NAMES[int(p.relief[b])]
        prm = p.relief_params[b].numpy()
        gx, gy = fd_gradient(name, x, y, prm)
        inv = 1.0 / np.sqrt(gx**2 + gy**2 + 1.0)
        ref = AMBIENT + (1 - AMBIENT) * np.maximum(0.0, (-gx * lx - gy * ly + lz) * inv)
        cx, cy = fd_gradient(name, x, y, prm, 1e-4)
        smooth = np.abs(gx - cx) + np.abs(gy - cy) < 1e-5
        np.testing.assert_allclose(s.shading[b, 0].numpy()[smooth], ref[smooth], atol=1e-6)
        assert s.albedo[b].std() > 0 and math.isfinite(float(s.shading[b].sum()))
