"""``lasagna.distill.adam.Adam``: torch.optim.Adam's updates bit for bit, its state_dict both ways, the algorithm
against numpy float64 (Kingma & Ba 2015, Algorithm 1, with torch's ε outside the bias-corrected root), and no
``torch._dynamo`` import (the reason it exists)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.distill.adam import Adam

ROOT = Path(__file__).resolve().parents[2]


def _params(seed: int, dtype: torch.dtype) -> list[torch.nn.Parameter]:
    g = torch.Generator().manual_seed(seed)
    return [torch.nn.Parameter(torch.randn(shape, generator=g, dtype=dtype)) for shape in ((3, 1, 5, 4), (7,))]


def _grads(step: int, params, seed: int) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed * 1000 + step)
    return [torch.randn(p.shape, generator=g, dtype=p.dtype) * (10.0 ** (step % 5 - 2)) for p in params]


def _run(opt_cls, params, steps: int, seed: int, lrs=(0.03, 0.01, 0.1)):
    opt = opt_cls(params, lr=lrs[0])
    _continue(opt, params, 0, steps, seed, lrs)
    return opt


def _continue(opt, params, start: int, steps: int, seed: int, lrs=(0.03, 0.01, 0.1)) -> None:
    for step in range(start, start + steps):
        opt.param_groups[0]["lr"] = lrs[step % len(lrs)]  # a schedule, as the per-image runs set it
        opt.zero_grad(set_to_none=True)
        for p, g in zip(params, _grads(step, params, seed), strict=True):
            p.grad = g.clone()
        opt.step()


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), steps=st.integers(1, 30), double=st.booleans())
def test_updates_equal_torch_adam_bit_for_bit(seed, steps, double):
    dtype = torch.float64 if double else torch.float32
    ours, theirs = _params(seed, dtype), _params(seed, dtype)
    a = _run(Adam, ours, steps, seed)
    b = _run(torch.optim.Adam, theirs, steps, seed)
    for p, q in zip(ours, theirs, strict=True):
        assert torch.equal(p, q)
    sa, sb = a.state_dict(), b.state_dict()
    assert sa["param_groups"] == sb["param_groups"]
    for i in sb["state"]:
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(sa["state"][i][key], sb["state"][i][key]), key


@pytest.mark.parametrize("direction", ["torch to ours", "ours to torch"])
def test_a_state_dict_moves_between_the_two(direction):
    """A checkpoint of a run with either optimiser resumes in the other to the same bits as an uninterrupted run."""
    first, second = (torch.optim.Adam, Adam) if direction == "torch to ours" else (Adam, torch.optim.Adam)
    whole = _params(5, torch.float32)
    _run(torch.optim.Adam, whole, 12, 5)
    split = _params(5, torch.float32)
    state = _run(first, split, 7, 5).state_dict()
    resumed = second(split, lr=1.0)
    resumed.load_state_dict(state)
    _continue(resumed, split, 7, 5, 5)
    for p, q in zip(split, whole, strict=True):
        assert torch.equal(p, q)


def test_the_algorithm_against_numpy_float64():
    """m ← β₁m + (1−β₁)g, v ← β₂v + (1−β₂)g², θ ← θ − lr·(m/(1−β₁ᵗ)) / (√(v/(1−β₂ᵗ)) + ε)."""
    params = _params(3, torch.float64)
    theta = [p.detach().numpy().copy() for p in params]
    m = [np.zeros_like(t) for t in theta]
    v = [np.zeros_like(t) for t in theta]
    lrs = (0.03, 0.01, 0.1)
    _run(Adam, params, 25, 3, lrs)
    for step in range(25):
        t = step + 1
        for i, g in enumerate(_grads(step, params, 3)):
            g = g.numpy()
            m[i] = 0.9 * m[i] + 0.1 * g
            v[i] = 0.999 * v[i] + 0.001 * g * g
            m_hat, v_hat = m[i] / (1 - 0.9**t), v[i] / (1 - 0.999**t)
            theta[i] = theta[i] - lrs[step % 3] * m_hat / (np.sqrt(v_hat) + 1e-8)
    for p, t in zip(params, theta, strict=True):
        np.testing.assert_allclose(p.detach().numpy(), t, rtol=0, atol=1e-12)


def test_a_parameter_without_a_gradient_is_left_alone():
    a, b = torch.nn.Parameter(torch.ones(3)), torch.nn.Parameter(torch.ones(3))
    opt = Adam([a, b], lr=0.1)
    a.grad = torch.ones(3)
    opt.step()
    assert torch.equal(b, torch.ones(3)) and b not in opt.state
    assert torch.allclose(a, torch.full((3,), 0.9))  # the first step moves by lr·sign(g) (to ε)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="empty parameter list"):
        Adam([], lr=0.1)
    opt = Adam([torch.nn.Parameter(torch.ones(2))], lr=0.1)
    other = torch.optim.Adam([torch.nn.Parameter(torch.ones(2)), torch.nn.Parameter(torch.ones(2))], lr=0.1)
    with pytest.raises(ValueError, match="different number"):
        opt.load_state_dict(other.state_dict())
    amsgrad = torch.optim.Adam([torch.nn.Parameter(torch.ones(2))], lr=0.1, amsgrad=True)
    with pytest.raises(ValueError, match="AMSGrad"):
        opt.load_state_dict(amsgrad.state_dict())


def test_a_per_image_run_imports_no_dynamo():
    """torch.optim's first call imports torch._dynamo (1.1–1.4 s); a per-image distillation never does."""
    code = (
        "import sys, torch\n"
        "from lasagna.distill import DistillSettings, Weights, distill_image\n"
        "from tests.distill.conftest import SHADING, gaussian_for\n"
        "base = torch.full((3, 4, 4), 0.5)\n"
        "s = DistillSettings(layer=SHADING, loss='sds', weights=Weights(), early_stop=None)\n"
        "distill_image(base, s, gaussian_for(base * 0.8), condition='x', steps=3)\n"
        "print('torch._dynamo' in sys.modules)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split()[-1] == "False"
