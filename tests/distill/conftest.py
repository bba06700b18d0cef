"""Closed-form problems for the distillation tests.

``shading_problem``: a base b (3, 4, 4) and a target 1-channel shading s (1, 4, 4); a Gaussian
prior whose every branch has mean μ = 2·(b·s) − 1 (the prior's [−1, 1] space) and a small variance,
so the SDS fixed point is the composite b·y = b·s, i.e. the multiplier y = s exactly (the blend is
multiply, so Σ_c b_c²(y − s) = 0 at the fixed point).
"""

from __future__ import annotations

import pytest
import torch

from lasagna.generators import LayerSpec
from lasagna.priors import GaussianPrior

SHADING = LayerSpec(blend="multiply", channels=1, range=(0.0, 2.0))
VARIANCE = 1e-3


def gaussian_for(images: torch.Tensor, labels=("x",), variance: float = VARIANCE) -> GaussianPrior:
    """A Gaussian prior at ``images``' size whose labels (and unconditional branch) all have mean ``images``."""
    mu = (images * 2 - 1).to(torch.float64).reshape(-1)
    shape = tuple(images.shape)
    return GaussianPrior(
        shape, {lab: mu for lab in labels}, {lab: variance for lab in labels}, unconditional=(mu, variance)
    )


@pytest.fixture(scope="session")
def shading_problem():
    g = torch.Generator().manual_seed(0)
    base = 0.3 + 0.6 * torch.rand(3, 4, 4, generator=g)
    shading = 0.4 + 1.0 * torch.rand(1, 4, 4, generator=g)
    return base, shading, gaussian_for(base * shading)
