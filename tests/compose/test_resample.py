"""Resampling between image and working sizes: Pillow and numpy float64 references."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from lasagna.compose.resample import downsample, upsample, working_size


@pytest.mark.parametrize(
    "hw,side,expected",
    [((256, 256), 64, (64, 64)), ((512, 384), 64, (64, 48)), ((30, 20), 64, (30, 20)), ((1000, 3), 64, (64, 1))],
)
def test_working_size(hw, side, expected):
    assert working_size(*hw, side) == expected


def test_working_size_rejects_zero():
    with pytest.raises(ValueError, match="working side must be ≥ 1"):
        working_size(10, 10, 0)


@pytest.mark.parametrize("size", [(64, 64), (40, 24)])
def test_downsample_matches_pillow_bilinear(size):
    # PyTorch's antialiased bilinear is Pillow's BILINEAR resize (a triangle filter widened by the scale).
    rng = np.random.default_rng(0)
    x = rng.random((96, 128)).astype(np.float32)
    ref = np.asarray(Image.fromarray(x, mode="F").resize((size[1], size[0]), Image.Resampling.BILINEAR))
    got = downsample(torch.from_numpy(x)[None, None], size)[0, 0].numpy()
    np.testing.assert_allclose(got, ref, atol=1e-5)


def _bilinear_ref(y: np.ndarray, H: int, W: int) -> np.ndarray:
    h, w = y.shape

    def coords(n_out, n_in):
        c = (np.arange(n_out) + 0.5) * n_in / n_out - 0.5
        c = np.clip(c, 0, n_in - 1)
        i0 = np.floor(c).astype(int)
        i1 = np.minimum(i0 + 1, n_in - 1)
        return i0, i1, c - i0

    r0, r1, fr = coords(H, h)
    c0, c1, fc = coords(W, w)
    top = y[r0][:, c0] * (1 - fc) + y[r0][:, c1] * fc
    bot = y[r1][:, c0] * (1 - fc) + y[r1][:, c1] * fc
    return top * (1 - fr[:, None]) + bot * fr[:, None]


def test_upsample_is_half_pixel_bilinear():
    y = np.random.default_rng(1).random((8, 12))
    got = upsample(torch.from_numpy(y)[None, None], (32, 36))[0, 0].numpy()
    np.testing.assert_allclose(got, _bilinear_ref(y, 32, 36), atol=1e-12)


def test_same_size_is_identity():
    x = torch.rand(2, 3, 16, 16)
    assert downsample(x, (16, 16)) is x and upsample(x, (16, 16)) is x
