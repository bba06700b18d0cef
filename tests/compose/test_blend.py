"""Blend modes, kornia-style: one class per op — smoke, shapes, exceptions, references (numpy float64
from the W3C formulas, and Pillow on uint8), NaN behaviour, float64 gradcheck, in-place == pure."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image, ImageChops

from lasagna.compose.blend import (
    BLEND_FUNC,
    BLEND_INPLACE,
    BLEND_MODES,
    clamp_needed,
    get_blend,
    multiply,
    normal,
)
from lasagna.errors import LasagnaError
from tests.compose.numpy_ref import FORMULAS

DTYPES = [torch.float64, torch.float32, torch.float16, torch.bfloat16]


def tol(dtype: torch.dtype) -> float:
    """Absolute tolerance for values in [0, 1] after a blend (a few roundings of the dtype)."""
    return {torch.float64: 1e-12, torch.float32: 1e-6, torch.float16: 4e-3, torch.bfloat16: 3e-2}[dtype]


def inputs(c_src: int = 3, batch: tuple[int, ...] = (), dtype=torch.float64, seed: int = 0, h: int = 4, w: int = 5):
    g = torch.Generator().manual_seed(seed)
    cb = torch.rand(*batch, 3, h, w, generator=g, dtype=torch.float64).to(dtype)
    cs = torch.rand(*batch, c_src, h, w, generator=g, dtype=torch.float64).to(dtype)
    a = torch.rand(*batch, 1, h, w, generator=g, dtype=torch.float64).to(dtype)
    return cb, cs, a


def pil_rgb(x: np.ndarray) -> Image.Image:
    return Image.fromarray(np.ascontiguousarray(x.transpose(1, 2, 0)), "RGB")


def u8(x: torch.Tensor) -> np.ndarray:
    return np.rint(x.clamp(0, 1).double().numpy() * 255).astype(np.int64)


class _BlendTests:
    name: str

    @property
    def fn(self):
        return BLEND_FUNC[self.name]

    @property
    def fn_(self):
        return BLEND_INPLACE[self.name]

    def test_smoke(self):
        cb, cs, a = inputs(dtype=torch.float32)
        out = self.fn(cb, cs, a)
        assert out.shape == cb.shape and out.dtype == torch.float32
        assert not torch.equal(out, cb)

    @pytest.mark.parametrize("c_src", [1, 3])
    @pytest.mark.parametrize("alpha", ["tensor", "float", "none", "0-d", "batch-opacity"])
    def test_cardinality_and_broadcast(self, c_src, alpha):
        cb, cs, a = inputs(c_src=c_src, batch=(2,))
        a = {
            "tensor": a,
            "float": 0.25,
            "none": None,
            "0-d": torch.tensor(0.5, dtype=torch.float64),
            "batch-opacity": torch.rand(2, 1, 1, 1, dtype=torch.float64),
        }[alpha]
        out = self.fn(cb, cs[0], a)  # source without batch dim broadcasts over the backdrop's batch
        assert out.shape == (2, 3, 4, 5)
        expect = FORMULAS[self.name](
            cb.numpy(),
            np.broadcast_to(cs[0].numpy(), (2, 3, 4, 5)),
            1.0 if a is None else (a.numpy() if isinstance(a, torch.Tensor) else a),
        )
        np.testing.assert_allclose(out.numpy(), expect, atol=1e-12)

    def test_batch_of_sources_grows_output(self):
        cb, cs, a = inputs(batch=(3,))
        out = self.fn(cb[0], cs, a)
        assert out.shape == (3, 3, 4, 5)
        with pytest.raises(LasagnaError, match="cannot grow its output"):
            self.fn_(cb[0].clone(), cs, a)

    @pytest.mark.parametrize(
        "bad, match",
        [
            ("cs_channels", "Cs has 2 channels"),
            ("cs_size", "expected the same height and width"),
            ("cb_ndim", "expected \\(..., C, h, w\\)"),
            ("cb_channels", "Cb has 4 channels"),
            ("a_channels", "a has shape"),
            ("a_range", "expected a number in \\[0, 1\\]"),
            ("dtype", "expected one dtype"),
            ("int", "expected a floating-point tensor"),
            ("batch", "do not broadcast"),
        ],
    )
    def test_exception(self, bad, match):
        cb, cs, a = inputs()
        args = {
            "cs_channels": (cb, cs[:2], a),
            "cs_size": (cb, cs[..., :3], a),
            "cb_ndim": (cb[0], cs, a),
            "cb_channels": (torch.rand(4, 4, 5, dtype=torch.float64), cs, a),
            "a_channels": (cb, cs, cs),
            "a_range": (cb, cs, 1.5),
            "dtype": (cb, cs.float(), a),
            "int": (cb, (cs * 9).long(), a),
            "batch": (cb.expand(2, 3, 4, 5), cs.expand(3, 3, 4, 5), a),
        }[bad]
        with pytest.raises(LasagnaError, match=match) as info:
            self.fn(*args)
        assert str(info.value).startswith(self.name.replace("-", "_") + ":")

    @pytest.mark.parametrize("dtype", DTYPES)
    @pytest.mark.parametrize("c_src", [1, 3])
    def test_reference_numpy(self, dtype, c_src):
        cb, cs, a = inputs(c_src=c_src, dtype=dtype, seed=1)
        out = self.fn(cb, cs, a)
        cb64, cs64, a64 = (t.double().numpy() for t in (cb, cs, a))
        expect = FORMULAS[self.name](cb64, np.broadcast_to(cs64, cb64.shape), a64)
        np.testing.assert_allclose(out.double().numpy(), expect, atol=tol(dtype))

    def test_reference_values(self):
        # Hand-computed from the W3C formulas: Cb = 0.5, Cs = 0.25, α = 0.5.
        expect = {"normal": 0.375, "multiply": 0.3125, "screen": 0.5625, "plus": 0.625}[self.name]
        out = self.fn(torch.full((3, 1, 1), 0.5), torch.full((1, 1, 1), 0.25), torch.full((1, 1, 1), 0.5))
        assert torch.equal(out, torch.full((3, 1, 1), expect))

    @pytest.mark.parametrize("dtype", DTYPES)
    @pytest.mark.parametrize("alpha", ["tensor", "float", "none", "0-d"])
    @pytest.mark.parametrize("c_src", [1, 3])
    def test_inplace_equals_pure(self, dtype, alpha, c_src):
        cb, cs, a = inputs(c_src=c_src, batch=(2,), dtype=dtype, seed=2)
        a = {"tensor": a, "float": 0.375, "none": None, "0-d": torch.tensor(0.625, dtype=dtype)}[alpha]
        pure = self.fn(cb, cs, a)
        out = cb.clone()
        assert self.fn_(out, cs, a) is out
        assert torch.equal(out, pure)  # bitwise

    def test_pure_does_not_modify_inputs(self):
        cb, cs, a = inputs()
        copies = [t.clone() for t in (cb, cs, a)]
        out = self.fn(cb, cs, None)
        out.add_(1)  # the result is a fresh tensor, even for an opaque normal source
        assert all(torch.equal(t, c) for t, c in zip((cb, cs, a), copies))

    def test_gradcheck(self):
        cb, cs, a = (t.requires_grad_() for t in inputs(seed=3))
        assert torch.autograd.gradcheck(self.fn, (cb, cs, a))
        cs1 = inputs(c_src=1, seed=4)[1].requires_grad_()
        assert torch.autograd.gradcheck(self.fn, (cb, cs1, a))

    @pytest.mark.parametrize("edge", [0.0, 1.0])
    def test_gradients_finite_at_alpha_edges(self, edge):
        cb, cs, _ = inputs(seed=5)
        a = torch.full((1, 4, 5), edge, dtype=torch.float64, requires_grad=True)
        cs = torch.zeros_like(cs).requires_grad_()  # a multiplier of 0 too
        cb.requires_grad_()
        self.fn(cb, cs, a).sum().backward()
        for t in (cb, cs, a):
            assert torch.isfinite(t.grad).all()

    def test_nan_propagates_where_touched(self):
        # Policy (blend.py): IEEE arithmetic, no masking — a NaN source pixel is NaN even where α = 0.
        cb, cs, a = inputs(seed=6)
        cs[:, 1, 2] = float("nan")
        a[:, 1, 2] = 0.0
        out = self.fn(cb, cs, a)
        assert torch.isnan(out[:, 1, 2]).all()
        mask = torch.ones(4, 5, dtype=torch.bool)
        mask[1, 2] = False
        assert torch.isfinite(out[:, mask]).all()

    def test_nan_in_alpha_propagates(self):
        cb, cs, a = inputs(seed=7)
        a[0, 0, 0] = float("nan")
        out = self.fn(cb, cs, a)
        assert torch.isnan(out[:, 0, 0]).all() and torch.isfinite(out[:, 1:]).all()


class TestNormal(_BlendTests):
    name = "normal"

    def test_opaque_source_is_exact_and_hides_nan_below(self):
        cb, cs, _ = inputs()
        cb[:, 0, 0] = float("nan")
        assert torch.equal(normal(cb, cs, None), cs)

    def test_reference_pillow_alpha_composite(self):
        rng = np.random.default_rng(0)
        cb = rng.integers(0, 256, (3, 16, 16), dtype=np.uint8)
        rgba = rng.integers(0, 256, (4, 16, 16), dtype=np.uint8)
        backdrop = Image.fromarray(np.concatenate([cb, np.full((1, 16, 16), 255, np.uint8)]).transpose(1, 2, 0), "RGBA")
        pil = np.asarray(Image.alpha_composite(backdrop, Image.fromarray(rgba.transpose(1, 2, 0), "RGBA")))
        ours = normal(
            torch.from_numpy(cb / 255.0), torch.from_numpy(rgba[:3] / 255.0), torch.from_numpy(rgba[3:] / 255.0)
        )
        assert np.abs(u8(ours) - pil[..., :3].transpose(2, 0, 1).astype(np.int64)).max() <= 1


class TestMultiply(_BlendTests):
    name = "multiply"

    def test_reference_pillow(self):
        rng = np.random.default_rng(1)
        cb, cs = rng.integers(0, 256, (2, 3, 16, 16), dtype=np.uint8)
        pil = np.asarray(ImageChops.multiply(pil_rgb(cb), pil_rgb(cs))).transpose(2, 0, 1)
        ours = multiply(torch.from_numpy(cb / 255.0), torch.from_numpy(cs / 255.0))
        assert np.abs(u8(ours) - pil.astype(np.int64)).max() <= 1

    def test_reference_pillow_luminosity_with_mask(self):
        # A 1-channel multiplier with an alpha mask, the way Pillow can: multiply, then composite.
        rng = np.random.default_rng(2)
        cb = rng.integers(0, 256, (3, 16, 16), dtype=np.uint8)
        cs, m = rng.integers(0, 256, (2, 1, 16, 16), dtype=np.uint8)
        prod = ImageChops.multiply(pil_rgb(cb), pil_rgb(np.repeat(cs, 3, 0)))
        pil = np.asarray(Image.composite(prod, pil_rgb(cb), Image.fromarray(m[0], "L"))).transpose(2, 0, 1)
        ours = multiply(torch.from_numpy(cb / 255.0), torch.from_numpy(cs / 255.0), torch.from_numpy(m / 255.0))
        assert np.abs(u8(ours) - pil.astype(np.int64)).max() <= 1

    def test_factor_above_one_brightens(self):
        out = multiply(torch.full((3, 1, 1), 0.25), torch.full((1, 1, 1), 2.0), 0.5)
        assert torch.allclose(out, torch.full((3, 1, 1), 0.375))


class TestScreen(_BlendTests):
    name = "screen"

    def test_reference_pillow(self):
        rng = np.random.default_rng(3)
        cb, cs = rng.integers(0, 256, (2, 3, 16, 16), dtype=np.uint8)
        pil = np.asarray(ImageChops.screen(pil_rgb(cb), pil_rgb(cs))).transpose(2, 0, 1)
        ours = BLEND_FUNC["screen"](torch.from_numpy(cb / 255.0), torch.from_numpy(cs / 255.0))
        assert np.abs(u8(ours) - pil.astype(np.int64)).max() <= 1


class TestPlus(_BlendTests):
    name = "plus"

    def test_reference_pillow(self):
        rng = np.random.default_rng(4)
        cb, cs = rng.integers(0, 256, (2, 3, 16, 16), dtype=np.uint8)
        pil = np.asarray(ImageChops.add(pil_rgb(cb), pil_rgb(cs))).transpose(2, 0, 1)  # clips at 255
        ours = BLEND_FUNC["plus"](torch.from_numpy(cb / 255.0), torch.from_numpy(cs / 255.0)).clamp(0, 1)
        assert np.abs(u8(ours) - pil.astype(np.int64)).max() <= 1


def test_table_is_complete():
    assert set(BLEND_FUNC) == set(BLEND_INPLACE) == set(BLEND_MODES)
    assert {"normal", "multiply", "screen", "plus", "overlay", "color-dodge", "hue", "luminosity"} <= set(BLEND_MODES)
    assert len(BLEND_MODES) == 28  # W3C Compositing Level 1's sixteen, Porter–Duff plus, Photoshop's other eleven
    assert get_blend("plus") is BLEND_FUNC["plus"] and get_blend("plus", inplace=True) is BLEND_INPLACE["plus"]


def test_table_matches_document_names():
    blend_names = pytest.importorskip("lasagna.document.blend")
    assert set(blend_names.BLEND_MODES) == set(BLEND_MODES)


def test_unknown_blend_lists_valid_ones():
    with pytest.raises(
        LasagnaError, match="unknown blend 'grain-merge'; expected one of normal, multiply, screen, plus, "
    ):
        get_blend("grain-merge")


@pytest.mark.parametrize(
    "blend, lo, hi, expect",
    [
        ("normal", 0.0, 1.0, (False, False)),
        ("screen", 0.0, 1.0, (False, False)),
        ("multiply", 0.0, 1.0, (False, False)),
        ("multiply", 0.0, 2.0, (False, True)),
        ("multiply", -0.5, 1.0, (True, False)),
        ("plus", 0.0, 1.0, (False, True)),
        ("plus", -1.0, 0.0, (True, False)),
        ("normal", float("nan"), 1.0, (True, True)),
        ("darken", 0.0, 1.0, (False, False)),
        ("difference", 0.0, 1.0, (False, False)),
        ("soft-light", 0.0, 1.0, (True, True)),
        ("hue", 0.0, 1.0, (True, True)),
    ],
)
def test_clamp_needed(blend, lo, hi, expect):
    assert clamp_needed(blend, lo, hi) == expect


unit = st.floats(0.0, 1.0, allow_nan=False, width=32)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(
    st.sampled_from(["normal", "multiply", "screen", "darken", "lighten", "difference"]),
    st.sampled_from(DTYPES),
    unit,
    unit,
    unit,
)
def test_no_clamp_needed_means_in_range(blend, dtype, cb, cs, a):
    # The clamp-skip proof (blend.py): in-range inputs stay in [0, 1] after rounding, in every dtype.
    assert clamp_needed(blend, 0.0, 1.0) == (False, False)
    cbt, cst = torch.tensor([[[cb]]] * 3, dtype=dtype), torch.tensor([[[cs]]], dtype=dtype)
    for alpha in (torch.tensor([[[a]]], dtype=dtype), float(torch.tensor(a, dtype=dtype)), None):
        out = BLEND_FUNC[blend](cbt, cst, alpha)
        assert bool(((out >= 0) & (out <= 1)).all()), (out, alpha)
