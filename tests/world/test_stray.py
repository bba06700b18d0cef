"""Stray illumination (lasagna.world.stray): each scene's gain is one of the three closed forms the module names,
with parameters in its declared ranges, checked by least-squares fits in numpy float64; it falls on the walls
alone about as often as declared; probability 0 is no gain; the draws are a function of the generator."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lasagna.world import stray
from lasagna.world.stray import stray_gain

SIDE = 24


def coords(side: int = SIDE) -> tuple[np.ndarray, np.ndarray]:
    c = (np.arange(side) + 0.5 - side / 2) * (2.0 / side)
    y, x = np.meshgrid(c, c, indexing="ij")
    return x.ravel(), y.ravel()


def residual(design: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, float]:
    coef, *_ = np.linalg.lstsq(design, values, rcond=None)
    return coef, float(np.abs(design @ coef - values).max())


def kind_of(gain: np.ndarray) -> str:
    """Which closed form ``gain`` (flattened SIDE²) is, its fitted parameters checked against the declared ranges."""
    x, y = coords()
    one = np.ones_like(x)
    coef, err = residual(np.stack([one, x, y], 1), np.log(gain))
    if err < 1e-5:  # log G = s (x cos θ + y sin θ): a plane through 0
        slope = math.hypot(coef[1], coef[2])
        assert abs(coef[0]) < 1e-5
        assert stray.GRADIENT_LOG_SLOPE[0] - 1e-5 <= slope <= stray.GRADIENT_LOG_SLOPE[1] + 1e-5
        return "gradient"
    coef, err = residual(np.stack([one, (x * x + y * y) / 2], 1), gain)
    if err < 1e-5:  # G = 1 − v r²/2
        assert abs(coef[0] - 1) < 1e-5
        assert stray.VIGNETTE_DEPTH[0] - 1e-5 <= -coef[1] <= stray.VIGNETTE_DEPTH[1] + 1e-5
        return "vignette"
    # G − 1 = b exp(−|p − c|²/(2σ²)): log(G − 1) is a paraboloid with equal x² and y² coefficients −1/(2σ²)
    lifted = gain - 1
    keep = lifted > 1e-3  # the Gaussian's far tail underflows the float32 gain's resolution
    coef, err = residual(np.stack([one, x, y, x * x + y * y], 1)[keep], np.log(lifted[keep]))
    assert err < 1e-2, "neither a gradient, a vignette nor a pool"
    sigma = math.sqrt(-1 / (2 * coef[3]))
    assert stray.POOL_WIDTH[0] - 1e-3 <= sigma <= stray.POOL_WIDTH[1] + 1e-3
    assert lifted.max() <= stray.POOL_GAIN[1] + 1e-5
    return "pool"


def test_every_gain_is_one_of_the_closed_forms_in_its_ranges():
    mask = torch.zeros(300, 1, SIDE, SIDE, dtype=torch.float64)  # no objects: the whole gain is seen
    gains = stray_gain(mask, torch.Generator().manual_seed(1)).numpy().reshape(300, -1)
    assert (gains > 0).all()
    kinds = [kind_of(g) for g in gains]
    for name in stray.KINDS:  # each drawn about a third of the time (300 draws: ±5 σ ≈ ±0.14)
        assert 0.19 < kinds.count(name) / len(kinds) < 0.47, name


def test_the_gain_falls_on_the_walls_only_about_as_often_as_declared():
    mask = torch.zeros(400, 1, SIDE, SIDE)
    mask[:, :, 8:16, 8:16] = 1  # one object in the middle of each scene
    gains = stray_gain(mask, torch.Generator().manual_seed(2))
    on_object = gains[:, 0, 8:16, 8:16].flatten(1)
    walls_only = (on_object == 1).all(1).float().mean().item()
    assert abs(walls_only - stray.WALLS_ONLY) < 0.1  # ±4 σ of 400 draws
    assert (gains[:, 0, :8] != 1).any(1).any(1).all()  # every scene's background is lit by its gain


def test_probability_zero_is_no_gain_and_the_same_draws():
    mask = torch.zeros(8, 1, SIDE, SIDE)
    a, b = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    assert torch.equal(stray_gain(mask, a, 0.0), torch.ones_like(mask))
    stray_gain(mask, b, 1.0)
    assert torch.equal(a.get_state(), b.get_state())  # as many draws whatever the outcome: a run resumes the same


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_gain_follows_the_mask_and_is_reproducible(dtype):
    mask = torch.zeros(4, 1, 10, 16, dtype=dtype)
    one = stray_gain(mask, torch.Generator().manual_seed(5))
    two = stray_gain(mask, torch.Generator().manual_seed(5))
    assert one.dtype == dtype and one.shape == (4, 1, 10, 16) and torch.equal(one, two)
