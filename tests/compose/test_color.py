"""sRGB transfer functions: reference values, round trip, gradients at 0, dtypes, NaN, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.compose.color import linear_to_srgb, srgb_to_linear
from lasagna.errors import LasagnaError

# Closed forms of IEC 61966-2-1 evaluated by hand in float64:
# decode(0.5) = (0.555/1.055)^2.4, decode(0.04045) = 0.04045/12.92, decode(1) = 1.
REFERENCE = [
    (0.0, 0.0),
    (0.02, 0.02 / 12.92),
    (0.04045, 0.04045 / 12.92),
    (0.5, (0.555 / 1.055) ** 2.4),
    (0.73, (0.785 / 1.055) ** 2.4),
    (1.0, 1.0),
]


@pytest.mark.parametrize("encoded, linear", REFERENCE)
def test_reference_values(encoded, linear):
    x = torch.tensor(encoded, dtype=torch.float64)
    assert abs(float(srgb_to_linear(x)) - linear) <= 1e-15


def test_known_constant():
    # The widely tabulated value: sRGB 0.5 is 21.404 % linear light.
    half = torch.tensor(0.5, dtype=torch.float64)
    assert float(srgb_to_linear(half)) == pytest.approx(0.21404114048223255, abs=1e-16)


def test_encode_reference_values():
    y = torch.tensor([0.0, 0.001, 0.0031308, 0.2, 1.0], dtype=torch.float64)
    expect = np.array([0.0, 0.01292, 0.0031308 * 12.92, 1.055 * 0.2 ** (1 / 2.4) - 0.055, 1.0])
    np.testing.assert_allclose(linear_to_srgb(y).numpy(), expect, atol=1e-15)


def test_odd_symmetric_extension():
    x = torch.tensor([0.01, 0.3, 1.5], dtype=torch.float64)
    assert torch.equal(srgb_to_linear(-x), -srgb_to_linear(x))
    assert torch.equal(linear_to_srgb(-x), -linear_to_srgb(x))


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.floats(-2.0, 2.0, allow_nan=False))
def test_round_trip_float64(v):
    x = torch.tensor(v, dtype=torch.float64)
    between = 0.0031308 * 12.92 <= abs(v) <= 0.04045  # the standard's two segments do not meet here
    assert abs(float(linear_to_srgb(srgb_to_linear(x))) - v) <= (3e-8 if between else 1e-14)
    assert abs(float(srgb_to_linear(linear_to_srgb(x))) - v) <= (3e-9 if abs(v) <= 0.0031308 * 1.001 else 1e-14)


@pytest.mark.parametrize("dtype, atol", [(torch.float32, 2e-7), (torch.float16, 2e-3), (torch.bfloat16, 1.6e-2)])
def test_dtypes_stay_and_agree(dtype, atol):
    x = torch.linspace(0, 1, 257, dtype=torch.float64)
    y = srgb_to_linear(x.to(dtype))
    assert y.dtype == dtype
    np.testing.assert_allclose(y.double().numpy(), srgb_to_linear(x).numpy(), atol=atol)


def test_gradcheck_and_finite_gradient_at_zero():
    x = torch.tensor([-0.7, -0.02, 0.0, 0.01, 0.04, 0.2, 0.9, 1.3], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(srgb_to_linear, (x,))
    y = torch.tensor([-0.5, -0.001, 0.0, 0.002, 0.01, 0.4, 1.2], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(linear_to_srgb, (y,))
    z = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    (srgb_to_linear(z).sum() + linear_to_srgb(z).sum()).backward()
    assert torch.allclose(z.grad, torch.full((3,), 1 / 12.92 + 12.92, dtype=torch.float64))


def test_nan_propagates():
    x = torch.tensor([float("nan"), 0.5])
    assert torch.isnan(srgb_to_linear(x)[0]) and torch.isnan(linear_to_srgb(x)[0])
    assert torch.isfinite(srgb_to_linear(x)[1])


def test_rejects_integer_tensors():
    with pytest.raises(LasagnaError, match="srgb_to_linear: expected a floating-point tensor, got torch.uint8"):
        srgb_to_linear(torch.zeros(3, dtype=torch.uint8))


def test_derivatives_match_autograd():
    from lasagna.compose.color import linear_to_srgb_derivative, srgb_to_linear_derivative

    x = torch.tensor(
        [-1.2, -0.3, -0.04, -0.001, 0.0, 0.002, 0.0031, 0.01, 0.04045, 0.05, 0.5, 1.0, 1.7],
        dtype=torch.float64,
        requires_grad=True,
    )
    for f, df in ((srgb_to_linear, srgb_to_linear_derivative), (linear_to_srgb, linear_to_srgb_derivative)):
        (g,) = torch.autograd.grad(f(x).sum(), x)
        assert torch.allclose(df(x.detach()), g, rtol=1e-12, atol=0)


def _set_luma_ref(c: np.ndarray, y: np.ndarray) -> np.ndarray:
    """W3C Compositing Level 1 SetLum/ClipColor (section 10.3) per pixel in float64, Rec. 709 weights."""
    w = np.array([0.2126, 0.7152, 0.0722])
    out = np.empty_like(c)
    for i in range(c.shape[0]):
        col = c[i] + (y[i] - w @ c[i])
        lum, n, x = w @ col, col.min(), col.max()
        if n < 0:
            col = lum + (col - lum) * lum / (lum - n)
        if x > 1:
            col = lum + (col - lum) * (1 - lum) / (x - lum)
        out[i] = col
    return out


def test_set_luma_is_setlum_with_rec709_weights():
    from lasagna.compose.color import luma, set_luma

    rng = np.random.default_rng(5)
    c = rng.uniform(-0.5, 1.5, (500, 3))
    y = rng.uniform(0.0, 1.0, 500)
    got = set_luma(torch.from_numpy(c.T.reshape(3, 1, 500)), torch.from_numpy(y.reshape(1, 1, 500)))
    np.testing.assert_allclose(got[:, 0].numpy().T, _set_luma_ref(c, y), atol=1e-12)
    np.testing.assert_allclose(luma(got)[0, 0].numpy(), y, atol=1e-12)  # the luma asked for, exactly
    assert float(got.min()) >= -1e-12 and float(got.max()) <= 1 + 1e-12  # in gamut
