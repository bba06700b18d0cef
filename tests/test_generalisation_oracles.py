"""The truth oracles of benchmarks/generalisation.py, against closed forms (they bound issue #10's targets)."""

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from generalisation import inflated_silhouettes, region_means  # noqa: E402

from lasagna.world.lighting import AMBIENT, LIGHTS  # noqa: E402


def test_a_disc_inflates_to_the_hemisphere():
    n, r, c = 96, 30.0, 47.5
    rows, cols = torch.meshgrid(
        torch.arange(n, dtype=torch.float64), torch.arange(n, dtype=torch.float64), indexing="ij"
    )
    x, y = (cols - c) / r, (c - rows) / r  # y up
    rho2 = x**2 + y**2
    index = torch.where(rho2 < 1.0, 0, -1)[None, None]
    got = inflated_silhouettes(index, ["top-left"])[0, 0].double()
    lx, ly, lz = LIGHTS["top-left"]
    z = (1.0 - rho2).clamp_min(0).sqrt()
    want = AMBIENT + (1 - AMBIENT) * (x * lx + y * ly + z * lz).clamp_min(0)
    inner = rho2 < 0.8**2  # near the rim a pixel grid's distance to a jagged edge is coarsest
    assert (got - want)[inner].abs().mean() < 0.02 and (got - want)[inner].abs().max() < 0.12
    wall = index[0, 0] < 0
    assert torch.allclose(got[wall], torch.tensor(AMBIENT + (1 - AMBIENT) * lz, dtype=torch.float64))


def test_region_means_are_each_regions_own_mean():
    g = torch.Generator().manual_seed(0)
    shading = torch.rand(2, 1, 8, 8, generator=g)
    index = torch.randint(-1, 3, (2, 1, 8, 8), generator=g)
    got = region_means(shading, index)
    for b in range(2):
        for k in index[b].unique():
            where = index[b] == k
            assert torch.allclose(got[b][where], shading[b][where].mean().expand(int(where.sum())))
