"""Procedural textures: ranges, closed forms in numpy, the lattice hash."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.world.paint import PHOTOS
from lasagna.world.textures import (
    N_PARAMS,
    TEXTURE_NAMES,
    TEXTURES,
    evaluate,
    hash01,
    sample_params,
    value_noise,
)


def points(n: int, seed: int, scale: float = 1.0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    p = (torch.rand(3, n, generator=g, dtype=torch.float64) * 2 - 1) * scale
    return tuple(p.to(dtype))


def params_for(family: str, n: int, seed: int = 0) -> torch.Tensor:
    u = np.random.default_rng(seed).random(8)
    return torch.from_numpy(sample_params(family, u, lo=0.3)).float().expand(n, N_PARAMS)


@pytest.mark.parametrize("family", TEXTURE_NAMES)
@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_every_family_is_in_unit_range_and_varies(family, seed):
    p = points(4096, seed)
    prm = params_for(family, 4096, seed)
    v = TEXTURES[family].pattern(p, prm, torch.full((4096,), seed, dtype=torch.int64))
    assert v.shape == (4096,) and v.dtype == torch.float32
    assert v.min() >= 0 and v.max() <= 1 and torch.isfinite(v).all()
    # A pattern, not a constant; a photograph may show a calm region (sky, a page's margin) at any scale.
    assert v.max() - v.min() > (0.1 if family in PHOTOS else 0.3)


class TestClosedForms:
    def test_stripes(self):
        p = points(1000, 1, dtype=torch.float64)
        prm = params_for("stripes", 1000, 2).double()
        f, u, o, duty = prm[0, 0].item(), prm[0, 1:4].numpy(), prm[0, 4:7].numpy(), prm[0, 7].item()
        x = np.stack([c.numpy() for c in p], 1)
        s = ((x + o) * f) @ u
        ref = (s - np.floor(s) < duty).astype(float)
        got = TEXTURES["stripes"].pattern(p, prm, torch.zeros(1000, dtype=torch.int64)).numpy()
        assert np.array_equal(got, ref)

    def test_checker(self):
        p = points(1000, 3, dtype=torch.float64)
        prm = params_for("checker", 1000, 4).double()
        f, o = prm[0, 0].item(), prm[0, 4:7].numpy()
        x = np.stack([c.numpy() for c in p], 1)
        ref = np.floor((x + o) * f).sum(1) % 2
        got = TEXTURES["checker"].pattern(p, prm, torch.zeros(1000, dtype=torch.int64)).numpy()
        assert np.array_equal(got, ref)

    def test_value_noise_interpolates_the_lattice(self):
        # At integer points value noise equals the hashed lattice value (smoothstep weights are 0/1).
        ijk = torch.tensor([[0, 0, 0], [3, -2, 5], [-7, 1, 1]], dtype=torch.int64)
        seed = torch.full((3,), 42, dtype=torch.int64)
        v = value_noise(tuple(ijk.T.double()), seed)
        ref = hash01(ijk[:, 0], ijk[:, 1], ijk[:, 2], seed, torch.float64)
        assert torch.equal(v, ref)


class TestHash:
    def test_uniform_and_deterministic(self):
        i = torch.arange(-20000, 20000, dtype=torch.int64)
        z = torch.zeros_like(i)
        h = hash01(i, z, z, torch.full_like(i, 9))
        assert torch.equal(h, hash01(i, z, z, torch.full_like(i, 9)))
        assert h.min() >= 0 and h.max() < 1
        counts = torch.histc(h, bins=10, min=0, max=1)
        # χ² against uniform with 9 degrees of freedom: 27.9 is its 99.9 % quantile.
        expected = len(i) / 10
        assert float(((counts - expected) ** 2 / expected).sum()) < 27.9

    def test_seed_changes_values(self):
        i = torch.arange(100, dtype=torch.int64)
        z = torch.zeros_like(i)
        a, b = hash01(i, z, z, torch.zeros_like(i)), hash01(i, z, z, torch.ones_like(i))
        assert (a != b).float().mean() > 0.95


def test_evaluate_groups_by_family():
    # Two surfaces with different families: each point gets its own surface's pattern.
    n = 500
    p = points(n, 5)
    fams = torch.tensor([TEXTURE_NAMES.index("checker"), TEXTURE_NAMES.index("dots")])
    prm = torch.stack([params_for("checker", 1, 0)[0], params_for("dots", 1, 1)[0]])
    seeds = torch.tensor([3, 4])
    surface = torch.arange(n) % 2
    got = evaluate(surface, fams, p, prm, seeds)
    for s, name in enumerate(("checker", "dots")):
        sel = surface == s
        ref = TEXTURES[name].pattern(
            tuple(c[sel] for c in p), prm[s].expand(int(sel.sum()), -1), seeds[s].expand(int(sel.sum()))
        )
        assert torch.equal(got[sel], ref)
