"""Painted texture families: closed forms in numpy float64, the glyph atlas, photographs as paint."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lasagna.world import paint
from lasagna.world.textures import N_PARAMS

F64 = torch.float64


def prm_row(f=2.0, phi=0.3, offset=(0.0, 0.0), duty=0.5, extra=0.2) -> torch.Tensor:
    row = torch.zeros(N_PARAMS, dtype=F64)
    row[0] = f
    row[1], row[2], row[3] = math.cos(phi), math.sin(phi), 0.0
    row[4], row[5] = offset
    row[7], row[9] = duty, extra
    return row


def grid(n=64, lo=-1.0, hi=1.0):
    x, y = np.meshgrid(np.linspace(lo, hi, n), np.linspace(lo, hi, n))
    return x.ravel(), y.ravel()


def run(fn, x, y, row, seed=5):
    n = len(x)
    p = (torch.from_numpy(x), torch.from_numpy(y), torch.zeros(n, dtype=F64))
    return fn(p, row.expand(n, -1), torch.full((n,), seed, dtype=torch.int64)).numpy()


def coords(x, y, row):
    f, phi = float(row[0]), math.atan2(float(row[2]), float(row[1]))
    xo, yo = x + float(row[4]), y + float(row[5])
    return f * (math.cos(phi) * xo + math.sin(phi) * yo), f * (-math.sin(phi) * xo + math.cos(phi) * yo)


def test_linear_gradient():
    x, y = grid()
    row = prm_row(f=0.8, phi=1.1, extra=0.1)
    ref = np.clip(0.5 + 0.5 * 0.8 * (math.cos(1.1) * x + math.sin(1.1) * y), 0, 1)
    np.testing.assert_allclose(run(paint.gradient, x, y, row), ref, atol=1e-12)


def test_radial_gradient():
    x, y = grid()
    row = prm_row(f=1.2, offset=(3.4, 7.9), extra=0.9)
    cx, cy = 3.4 % 2 - 1, 7.9 % 2 - 1
    ref = np.clip(1 - 0.5 * 1.2 * np.hypot(x - cx, y - cy), 0, 1)
    np.testing.assert_allclose(run(paint.gradient, x, y, row), ref, atol=1e-12)


def test_zigzag():
    x, y = grid(97)
    row = prm_row(f=3.0, phi=0.7, offset=(1.3, 2.2), duty=0.4, extra=0.25)
    a, b = coords(x, y, row)
    s = b + 0.75 * (1 - 2 * np.abs(np.mod(a, 2.0) - 1))
    ref = (np.mod(s, 1.0) < 0.4).astype(float)
    got = run(paint.zigzag, x, y, row)
    # Points within rounding of a stripe edge may fall either way.
    edge = np.minimum(np.abs(np.mod(s, 1.0) - 0.4), np.minimum(np.mod(s, 1.0), 1 - np.mod(s, 1.0))) < 1e-9
    assert np.array_equal(got[~edge], ref[~edge])


def test_hexagons_are_cells_of_one_tone_with_borders():
    row = prm_row(f=3.0, phi=0.0, duty=0.2)
    # Hexagon centres of the module's tiling (pointy-top, centres 1 apart): a = √3·s·(q + r/2), b = 1.5·s·r.
    s = 1 / math.sqrt(3)
    rng = np.random.default_rng(0)
    for q, r in [(0, 0), (2, -1), (-3, 4)]:
        ca, cb = s * math.sqrt(3) * (q + r / 2), 1.5 * s * r
        # Points well inside the cell (within 0.3 of the centre, apothem 0.5, border from 0.4) share one tone.
        ang, rad = rng.uniform(0, 2 * math.pi, 50), rng.uniform(0, 0.3, 50)
        a, b = ca + rad * np.cos(ang), cb + rad * np.sin(ang)
        v = run(paint.hexagons, a / 3.0, b / 3.0, row)
        assert np.all(v == v[0]) and 0.25 <= v[0] <= 1.0
        # Just inside each vertical edge (|a − ca| = 0.45 > 0.4) is border: 0.
        v = run(paint.hexagons, np.array([ca + 0.45, ca - 0.45]) / 3.0, np.array([cb, cb]) / 3.0, row)
        assert np.all(v == 0.0)


def test_cells_border_and_tones():
    x, y = grid(128)
    v = run(paint.cells, x, y, prm_row(f=4.0, duty=0.3))
    assert 0.05 < (v == 0).mean() < 0.5  # borders are a minority
    tones = v[v > 0]
    assert tones.min() >= 0.25 and tones.max() <= 1.0 and len(np.unique(tones)) >= 20  # one tone a cell


def test_deadleaves_statistics():
    # Piecewise constant (each pixel shows one leaf) with many leaves of many sizes.
    x, y = grid(128)
    v = run(paint.deadleaves, x, y, prm_row(f=3.0))
    assert v.min() >= 0 and v.max() <= 1
    img = v.reshape(128, 128)
    assert (np.abs(np.diff(img, axis=1)) == 0).mean() > 0.8  # mostly flat regions …
    assert len(np.unique(v)) >= 30  # … of many leaves


def test_glyph_atlas():
    atlas = paint.glyph_atlas()
    assert atlas.shape == (len(paint.GLYPHS), 32, 32) and atlas.dtype == F64
    ink = atlas.flatten(1).sum(1)
    assert (ink > 5).all() and atlas.min() >= 0 and atlas.max() <= 1
    flat = atlas.flatten(1)
    same = (flat[:, None] - flat[None]).abs().sum(-1) < 1e-9
    assert same.sum() == len(paint.GLYPHS)  # every glyph distinct (l and I differ in this font)


def test_glyphs_blank_cells_and_polarity():
    x, y = grid(128)
    dark = run(paint.glyphs, x, y, prm_row(f=4.0, duty=0.3, extra=0.1))
    light = run(paint.glyphs, x, y, prm_row(f=4.0, duty=0.3, extra=0.9))
    np.testing.assert_allclose(dark, 1 - light, atol=1e-12)
    assert 0.6 < dark.mean() < 0.98  # mostly paper, some ink


@pytest.mark.parametrize("family", sorted(paint.PHOTOS))
def test_photo_samples_the_photograph(family):
    images = paint.photo_stack(family)
    assert images.shape[0] == len(paint.PHOTOS[family]) and images.min() >= 0 and images.max() <= 1
    size = images.shape[-1]
    row = prm_row(f=1.0, phi=0.0, offset=(0.0, 0.0))
    # At a = (j)/(size − 1), b = 1 − i/(size − 1) (inside the first mirror period) the sample is pixel (i, j).
    i, j = np.array([3, 60, 100]), np.array([7, 64, 120])
    a, b = j / (size - 1), 1 - i / (size - 1)
    seed = 11
    v = run(paint.photo if family == "photo" else paint.naturephoto, a, b, row, seed=seed)
    from lasagna.world.noise import hash01

    s = torch.tensor([seed])
    k = int((hash01(s, s, torch.tensor([7]), s, F64) * len(paint.PHOTOS[family])).clamp_max(images.shape[0] - 1))
    np.testing.assert_allclose(v, images[k, i, j].numpy(), atol=1e-9)
    # Mirrored repeats: a and 2 − a sample the same column.
    w = run(paint.photo if family == "photo" else paint.naturephoto, 2.0 - a, b, row, seed=seed)
    np.testing.assert_allclose(v, w, atol=1e-9)


def test_plaid():
    x, y = grid(97)
    row = prm_row(f=2.5, phi=0.4, offset=(0.7, 1.9), duty=0.3, extra=0.6)
    a, b = coords(x, y, row)
    band_a, band_b = np.mod(a, 1.0) < 0.3, np.mod(b + 0.6, 1.0) < 0.15
    ref = 0.15 + 0.45 * band_a + 0.4 * band_b
    got = run(paint.plaid, x, y, row)
    edge = (np.minimum(np.abs(np.mod(a, 1.0) - 0.3), np.mod(a, 1.0)) < 1e-9) | (
        np.minimum(np.abs(np.mod(b + 0.6, 1.0) - 0.15), np.mod(b + 0.6, 1.0)) < 1e-9
    )
    np.testing.assert_allclose(got[~edge], ref[~edge], atol=1e-12)


def test_weave():
    x, y = grid(97)
    row = prm_row(f=2.0, phi=-0.6, offset=(0.2, 0.5), duty=0.3)
    a, b = coords(x, y, row)
    along_a = np.mod(np.floor(a) + np.floor(b), 2.0) < 0.5
    across = np.where(along_a, np.mod(3 * b, 1.0), np.mod(3 * a, 1.0))
    ref = np.where(across > 0.3, np.where(along_a, 0.9, 0.6), 0.0)
    got = run(paint.weave, x, y, row)
    edge = (np.abs(across - 0.3) < 1e-9) | (np.abs(a - np.round(a)) < 1e-9) | (np.abs(b - np.round(b)) < 1e-9)
    np.testing.assert_allclose(got[~edge], ref[~edge], atol=1e-12)


def test_scales_tones_and_rims():
    x, y = grid(129)
    row = prm_row(f=3.0, phi=0.2, duty=0.2)
    got = run(paint.scales, x, y, row)
    # Every point is covered by a scale: a dark rim (0) or a hashed tone in [0.3, 1].
    assert ((got == 0) | ((got >= 0.3) & (got <= 1.0))).all()
    assert 0.1 < (got == 0).mean() < 0.6  # rims are a visible share, not everything
    assert len(np.unique(np.round(got[got > 0], 9))) > 10  # a tone per scale
