"""Shared fixtures for the loss tests: small closed-form priors and a toy prior with parameters."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from lasagna.priors import GaussianPrior, NoiseSchedule, Prior

SHAPE = (3, 2, 2)
D = 12


@pytest.fixture(scope="session")
def gauss_params():
    """numpy parameters of two diagonal labels and an explicit, wider unconditional Gaussian."""
    rng = np.random.default_rng(0)
    mu_a, mu_b = rng.uniform(-0.5, 0.5, D), rng.uniform(-0.5, 0.5, D)
    var_a, var_b = rng.uniform(0.05, 0.2, D), rng.uniform(0.05, 0.2, D)
    mu_u, var_u = (mu_a + mu_b) / 2, np.maximum(var_a, var_b) + 0.1
    return {"a": (mu_a, var_a), "b": (mu_b, var_b), "u": (mu_u, var_u)}


def make_prior(params, explicit_uncond: bool) -> GaussianPrior:
    t = lambda x: torch.tensor(x)  # noqa: E731
    return GaussianPrior(
        SHAPE,
        {lab: t(params[lab][0]) for lab in ("a", "b")},
        {lab: t(params[lab][1]) for lab in ("a", "b")},
        unconditional=(t(params["u"][0]), t(params["u"][1])) if explicit_uncond else None,
    )


@pytest.fixture(scope="session")
def prior_u(gauss_params) -> GaussianPrior:
    """Labels a, b and an explicit single-Gaussian unconditional branch (closed-form everything)."""
    return make_prior(gauss_params, True)


@pytest.fixture(scope="session")
def prior_mix(gauss_params) -> GaussianPrior:
    """Labels a, b; the unconditional branch is their exact 50/50 mixture."""
    return make_prior(gauss_params, False)


def components(params, label: str, explicit_uncond: bool):
    """The numpy component list (weight, mean, variances) of one branch ("" = unconditional)."""
    if label:
        return [(1.0, *params[label])]
    if explicit_uncond:
        return [(1.0, *params["u"])]
    return [(0.5, *params["a"]), (0.5, *params["b"])]


class ConvPrior(Prior):
    """A toy prior with trainable parameters (a 3×3 conv and a label embedding), to prove that no
    gradient reaches a prior's parameters through any loss."""

    def __init__(self, shape=SHAPE, vocabulary=("a", "b")):
        super().__init__()
        self.schedule = NoiseSchedule()
        self.vocabulary = tuple(vocabulary)
        self.sample_shape = shape
        self.conv = nn.Conv2d(shape[0] * 2, shape[0], 3, padding=1)
        self.emb = nn.Embedding(len(vocabulary) + 1, shape[0])

    def _eps(self, z_t, t, label_idx, image):
        img = torch.zeros_like(z_t) if image is None else image.to(z_t.dtype) * 2 - 1
        x = self.conv(torch.cat([z_t, img], 1)) + self.emb(label_idx)[:, :, None, None]
        return torch.tanh(x) * (t.to(z_t.dtype)[:, None, None, None] / 1000)
