"""Resampling between image and working sizes: Pillow and numpy float64 references."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from lasagna.compose.color import luma
from lasagna.compose.resample import (
    downsample,
    gaussian_blur,
    guided_upsample,
    joint_bilateral_upsample,
    upsample,
    upsample_colour,
    working_size,
)


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


def _box_ref(x: np.ndarray, r: int) -> np.ndarray:
    h, w = x.shape
    out = np.empty_like(x)
    for i in range(h):
        for j in range(w):
            out[i, j] = x[max(0, i - r) : i + r + 1, max(0, j - r) : j + r + 1].mean()
    return out


def test_guided_upsample_matches_the_papers_algorithm():
    rng = np.random.default_rng(2)
    guide = rng.random((32, 32))
    y = rng.random((8, 8))
    r, eps = 1, 1e-2
    # He & Sun 2015, Alg. 2, with Pillow-equivalent reduction and half-pixel bilinear enlargement.
    g = downsample(torch.from_numpy(guide)[None, None], (8, 8))[0, 0].numpy()
    mi, my = _box_ref(g, r), _box_ref(y, r)
    a = (_box_ref(g * y, r) - mi * my) / (_box_ref(g * g, r) - mi * mi + eps)
    b = my - a * mi
    a, b = _box_ref(a, r), _box_ref(b, r)
    ref = _bilinear_ref(a, 32, 32) * guide + _bilinear_ref(b, 32, 32)
    got = guided_upsample(torch.from_numpy(y)[None, None], torch.from_numpy(guide)[None, None], r, eps)[0, 0].numpy()
    np.testing.assert_allclose(got, ref, atol=1e-12)


def test_guided_upsample_keeps_a_constant_and_follows_an_edge():
    guide = torch.zeros(1, 1, 32, 32, dtype=torch.float64)
    guide[..., 16:] = 1.0
    const = torch.full((1, 1, 8, 8), 0.7, dtype=torch.float64)
    torch.testing.assert_close(guided_upsample(const, guide), torch.full_like(guide, 0.7), atol=1e-12, rtol=0)
    step = downsample(guide * 0.5 + 0.25, (8, 8))  # a layer whose edge is the guide's, blurred by the reduction
    out = guided_upsample(step, guide, radius=1, eps=1e-4)
    blurry = upsample(step, (32, 32))
    truth = guide * 0.5 + 0.25
    assert (out - truth).abs().mean() < 0.5 * (blurry - truth).abs().mean()


def _jbu_ref(y: np.ndarray, guide: np.ndarray, small: np.ndarray, sigma: float, sigma_g: float) -> np.ndarray:
    """Kopf et al. 2007, eq. 2, pixel by pixel in float64: the 4×4 working-size cells nearest each full-size pixel's
    centre (clamped at the borders), weighted by their distance in cells and their reduced guide's difference."""
    c, h, w = y.shape
    big_h, big_w = guide.shape
    out = np.zeros((c, big_h, big_w))
    for i in range(big_h):
        for j in range(big_w):
            u, v = (i + 0.5) * h / big_h - 0.5, (j + 0.5) * w / big_w - 0.5
            num, den = np.zeros(c), 0.0
            for qi in range(int(np.floor(u)) - 1, int(np.floor(u)) + 3):
                for qj in range(int(np.floor(v)) - 1, int(np.floor(v)) + 3):
                    ci, cj = min(max(qi, 0), h - 1), min(max(qj, 0), w - 1)
                    wgt = np.exp(-((u - qi) ** 2 + (v - qj) ** 2) / (2 * sigma**2))
                    wgt *= np.exp(-((guide[i, j] - small[ci, cj]) ** 2) / (2 * sigma_g**2))
                    num += wgt * y[:, ci, cj]
                    den += wgt
            out[:, i, j] = num / den
    return out


@pytest.mark.parametrize("small_hw,big_hw", [((5, 7), (15, 21)), ((4, 6), (13, 9)), ((3, 3), (3, 3))])
def test_joint_bilateral_upsample_matches_kopf_et_al(small_hw, big_hw):
    rng = np.random.default_rng(4)
    y = rng.random((2, *small_hw))
    guide = rng.random(big_hw)
    sigma, sigma_g = 1.0, 0.2
    small = downsample(torch.from_numpy(guide)[None, None], small_hw)[0, 0].numpy()
    got = joint_bilateral_upsample(torch.from_numpy(y)[None], torch.from_numpy(guide)[None, None], sigma, sigma_g)
    ref = y if small_hw == big_hw else _jbu_ref(y, guide, small, sigma, sigma_g)
    np.testing.assert_allclose(got[0].numpy(), ref, atol=1e-12)


def test_joint_bilateral_upsample_stays_in_range_and_stops_at_an_edge():
    # A convex combination of the working-size values: never outside their range (property, random inputs).
    rng = np.random.default_rng(5)
    for _ in range(5):
        y = torch.from_numpy(rng.normal(size=(1, 3, 6, 5)))
        out = joint_bilateral_upsample(y, torch.from_numpy(rng.random((1, 1, 30, 17))))
        assert out.shape == (1, 3, 30, 17)
        lo, hi = y.amin(dim=(2, 3), keepdim=True), y.amax(dim=(2, 3), keepdim=True)
        assert bool(((out >= lo - 1e-12) & (out <= hi + 1e-12)).all())
    # A step of the guide inside a working-size cell: the layer, blurred by the reduction, is put back on the
    # guide's side of the step (far closer to the truth than bilinear), and a constant stays constant.
    guide = torch.zeros(1, 1, 32, 32, dtype=torch.float64)
    guide[..., 13:] = 1.0
    truth = guide * 0.5 + 0.25
    step = downsample(truth, (8, 8))
    out = joint_bilateral_upsample(step, guide)
    assert (out - truth).abs().mean() < 0.25 * (upsample(step, (32, 32)) - truth).abs().mean()
    const = torch.full((1, 1, 8, 8), 0.7, dtype=torch.float64)
    torch.testing.assert_close(joint_bilateral_upsample(const, guide), torch.full_like(guide, 0.7), atol=1e-12, rtol=0)


def test_joint_bilateral_upsample_works_at_most_at_its_cap(monkeypatch):
    # A guide longer than JBU_MAX_SIDE: the mean is taken at the capped size (the guide reduced to it), then enlarged
    # bilinearly; at or below the cap, the mean itself.
    import lasagna.compose.resample as resample

    rng = np.random.default_rng(6)
    y = torch.from_numpy(rng.random((1, 3, 4, 6)))
    guide = torch.from_numpy(rng.random((1, 1, 30, 45)))
    want = joint_bilateral_upsample(y, downsample(guide, (16, 24)))
    monkeypatch.setattr(resample, "JBU_MAX_SIDE", 24)
    got = resample.joint_bilateral_upsample(y, guide)
    torch.testing.assert_close(got, upsample(want, (30, 45)), atol=1e-12, rtol=0)
    assert got.shape == (1, 3, 30, 45)
    small = torch.from_numpy(rng.random((1, 1, 16, 24)))
    torch.testing.assert_close(resample.joint_bilateral_upsample(y, small), joint_bilateral_upsample(y, small))


def test_upsample_colour_carries_the_luma_in_gamut():
    # Colour over luminance: whatever the working-size colour, the enlarged colour's Rec. 709 luma is the full-size
    # luma (float64 numpy), every value in [0, 1]; alpha is the bilinear enlargement, clamped.
    rng = np.random.default_rng(3)
    layer = torch.from_numpy(rng.random((1, 4, 8, 6)))
    y = torch.from_numpy(rng.random((1, 1, 24, 18)))
    out = upsample_colour(layer, y)
    assert out.shape == (1, 4, 24, 18)
    c = out[0, :3].numpy()
    np.testing.assert_allclose(0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2], y[0, 0].numpy(), atol=1e-12)
    assert c.min() >= 0.0 and c.max() <= 1.0
    np.testing.assert_allclose(out[0, 3].numpy(), _bilinear_ref(layer[0, 3].numpy(), 24, 18), atol=1e-12)
    same = upsample_colour(layer, downsample(y, (8, 6)))  # equal sizes: only set to the luma, nothing filtered
    torch.testing.assert_close(luma(same[:, :3]), downsample(y, (8, 6)), atol=1e-12, rtol=0)


def test_upsample_colour_has_no_block_edges_and_follows_the_guide():
    # A two-colour layer at 8² whose edge is the guide's: enlarged 4×, its chroma changes at the guide's edge (not
    # smeared over a working pixel) and the gradient energy at working-pixel boundaries is no higher than elsewhere.
    guide = torch.linspace(0.2, 0.8, 32, dtype=torch.float64).view(1, 1, 1, 32).expand(1, 1, 32, 32).clone()
    guide[..., 13:] += 0.15  # an edge inside a working pixel (13 is not a multiple of 4)
    red, blue = torch.tensor([0.9, 0.2, 0.2]), torch.tensor([0.2, 0.3, 0.9])
    truth = torch.where(torch.arange(32).view(1, 1, 1, 32) >= 13, blue.view(1, 3, 1, 1), red.view(1, 3, 1, 1))
    truth = truth.to(torch.float64).expand(1, 3, 32, 32)
    small = downsample(torch.cat([truth, torch.ones(1, 1, 32, 32, dtype=torch.float64)], 1), (8, 8))
    out = upsample_colour(small, guide)[:, :3]
    chroma = out - luma(out)
    d = (chroma[..., 1:] - chroma[..., :-1]).pow(2).sum(dim=(0, 1, 2))  # (31,) energy between columns j, j + 1
    at_edge = int(d.argmax())
    assert at_edge == 12, f"the chroma's largest step is between columns {at_edge} and {at_edge + 1}; expected 12/13"
    rest = torch.cat([d[:12], d[13:]])
    boundaries = rest[[j for j in range(rest.numel()) if (j if j < 12 else j + 1) % 4 == 3]]
    assert float(boundaries.mean()) <= 1.5 * float(rest.mean())


@pytest.mark.parametrize("shape", [(1, 2, 1, 1), (1, 2, 1, 9), (1, 2, 7, 1), (1, 2, 6, 9)])
def test_gaussian_blur_matches_a_mirrored_float64_reference_and_keeps_a_one_pixel_side(shape):
    """``gaussian_blur``: each side blurred by the normalised Gaussian of radius min(⌈3σ⌉, side − 1) ≥ 1 with edges
    mirrored (numpy float64, ``np.pad(mode="reflect")``); a side of one pixel is left as it is (a 1×N or N×1 image,
    such as a 7×300 photograph's working input, blurs along its long side only instead of failing)."""
    import math

    sigma = 0.8
    x = torch.rand(*shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    want = x.numpy().copy()
    for axis in (3, 2):
        n = want.shape[axis]
        if n == 1:
            continue
        r = max(1, min(math.ceil(3 * sigma), n - 1))
        t = np.arange(-r, r + 1, dtype=np.float64)
        k = np.exp(-0.5 * (t / sigma) ** 2)
        k /= k.sum()
        pad = [(0, 0)] * 4
        pad[axis] = (r, r)
        padded = np.pad(want, pad, mode="reflect")
        want = sum(k[i] * np.take(padded, range(i, i + n), axis=axis) for i in range(2 * r + 1))
    np.testing.assert_allclose(gaussian_blur(x, sigma).numpy(), want, rtol=0, atol=1e-12)
