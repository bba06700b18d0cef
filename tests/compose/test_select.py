"""lasagna.compose.select: the lerp form of the per-pixel select equals torch.where bit for bit, values and
gradients, in every kernel that uses it (the half-precision path *is* torch.where)."""

import pytest
import torch

from lasagna.compose import select
from lasagna.compose.blend import W3C_B
from lasagna.compose.color import (
    linear_to_srgb,
    linear_to_srgb_derivative,
    srgb_to_linear,
    srgb_to_linear_derivative,
)

KINKS = torch.tensor([0.0, 0.25, 0.5, 1.0, -0.0, 0.04045, 0.0031308])


def _values(g: torch.Generator, n: int, dtype: torch.dtype) -> torch.Tensor:
    """Random values in [-1, 4] with every kink of the kernels mixed in, and a few large magnitudes."""
    x = torch.rand(n, generator=g, dtype=torch.float64) * 5.0 - 1.0
    x[: len(KINKS)] = KINKS.double()
    x[len(KINKS) : len(KINKS) + 3] = torch.tensor([1e6, -1e6, 1e12])
    return x[torch.randperm(n, generator=g)].to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("op", ["<=", "<", ">=", ">", "==", "!="])
def test_pick_is_where(dtype, op):
    g = torch.Generator().manual_seed(1)
    x = _values(g, 4096, dtype)
    a = _values(g, 4096, dtype).requires_grad_()
    b = _values(g, 4096, dtype).requires_grad_()
    w = select.step(op, x, 0.5)
    assert w.dtype == dtype and set(w.unique().tolist()) <= {0.0, 1.0}
    mask = {"<=": x <= 0.5, "<": x < 0.5, ">=": x >= 0.5, ">": x > 0.5, "==": x == 0.5, "!=": x != 0.5}[op]
    assert torch.equal(w.bool(), mask)
    got, want = select.pick(w, a, b), torch.where(mask, a, b)
    assert torch.equal(got, want)
    up = torch.randn(4096, generator=g, dtype=torch.float64).to(dtype)
    ga, gb = torch.autograd.grad(got, (a, b), up)
    wa, wb = torch.autograd.grad(want, (a, b), up)
    assert torch.equal(ga, wa) and torch.equal(gb, wb)


def _grid(g: torch.Generator, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
    """Colours in [-0.25, 1.5] with the modes' kinks (0, ¼, ½, 1) and grays mixed in."""
    x = torch.rand(shape, generator=g, dtype=torch.float64) * 1.75 - 0.25
    flat = x.view(-1)
    idx = torch.randperm(flat.numel(), generator=g)[: flat.numel() // 3]
    flat[idx] = torch.tensor([0.0, 0.25, 0.5, 1.0], dtype=torch.float64)[torch.arange(len(idx)) % 4]
    x[..., 1, :, :][:, :4] = x[..., 0, :, :][:, :4]  # a few grays (R = G = B) for SetSat and ClipColor
    x[..., 2, :, :][:, :4] = x[..., 0, :, :][:, :4]
    return x.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("mode", sorted(W3C_B))
def test_every_mode_equals_its_torch_where_form(mode, dtype, monkeypatch):
    g = torch.Generator().manual_seed(2)
    cb0, cs0 = _grid(g, (2, 3, 16, 16), dtype), _grid(g, (2, 3, 16, 16), dtype)
    up = torch.randn(2, 3, 16, 16, generator=g, dtype=torch.float64).to(dtype)

    def run():
        cb, cs = cb0.clone().requires_grad_(), cs0.clone().requires_grad_()
        out = W3C_B[mode](cb, cs)
        return (out, *torch.autograd.grad(out, (cb, cs), up))

    fast = run()
    monkeypatch.setattr(select, "FAST_DTYPES", ())  # every select through torch.where
    slow = run()
    for f, s in zip(fast, slow, strict=True):
        assert torch.equal(f, s)
        assert torch.isfinite(f).all()


@pytest.mark.parametrize("fn", [srgb_to_linear, linear_to_srgb, srgb_to_linear_derivative, linear_to_srgb_derivative])
def test_srgb_curves_equal_their_torch_where_form(fn, monkeypatch):
    g = torch.Generator().manual_seed(3)
    x0 = _values(g, 4096, torch.float32)
    fast = fn(x0)
    monkeypatch.setattr(select, "FAST_DTYPES", ())
    assert torch.equal(fast, fn(x0))


def test_half_precision_keeps_torch_where():
    x = torch.tensor([0.0, 20.0], dtype=torch.float16)
    assert select.step("<=", x, 0.25).dtype == torch.bool
    # soft-light of a large backdrop: its polynomial branch would overflow float16 where not selected
    out = W3C_B["soft-light"](x[None, :, None], torch.tensor([0.9], dtype=torch.float16)[None, :, None])
    assert torch.isfinite(out).all()
