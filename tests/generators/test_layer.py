"""The layer parametrisation: spec rules, the squash and its inverse, the inward clamp, the composite
against the W3C formulas in numpy float64, and the identity edit of every bundled preset."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.document.preset import load_preset
from lasagna.errors import LasagnaError
from lasagna.generators import LayerSpec, activate, clamp_inward, composite, inverse, split
from lasagna.numerics import IDENTITY_LOGIT

LAYERS = Path(__file__).resolve().parents[2] / "layers"
PRESETS = ("shading", "color", "light")

SHADING = LayerSpec(blend="multiply", channels=1, range=(0.0, 2.0))
COLOR = LayerSpec(blend="normal", channels=4)
LIGHT = LayerSpec(blend="plus", channels=3)


def np_composite(base: np.ndarray, layer: np.ndarray, blend: str) -> np.ndarray:
    """W3C Compositing Level 1 over an opaque backdrop, float64 (Cb + α(B(Cb, Cs) − Cb))."""
    if layer.shape[1] == 4:
        cs, a = layer[:, :3], layer[:, 3:]
    else:
        cs, a = layer, np.ones_like(layer[:, :1])
    mixed = {"normal": cs, "multiply": base * cs, "plus": base + cs, "screen": base + cs - base * cs}[blend]
    return base + a * (mixed - base)


class TestSpec:
    def test_from_presets(self):
        specs = {name: LayerSpec.from_preset(load_preset(LAYERS / name)) for name in PRESETS}
        assert specs["shading"] == SHADING and specs["light"] == LIGHT
        assert specs["color"] == COLOR.model_copy(update={"luminance": "base"})  # colour over luminance

    @pytest.mark.parametrize(
        "kwargs, match",
        [
            (dict(blend="normal", channels=3), "alpha"),
            (dict(blend="multiply", channels=1, range=(0.0, 0.5)), "does not contain 1.0"),
            (dict(blend="plus", channels=3, range=(0.1, 1.0)), "does not contain 0.0"),
            (dict(blend="normal", channels=4, range=(0.0, 2.0)), "only for multiply and plus"),
            (dict(blend="multiply", channels=1, range=(1.0, 1.0)), "lo < hi"),
            (dict(blend="multiply", channels=2), "channels"),
            (dict(blend="multiply", channels=1, extra=1), "extra"),
        ],
    )
    def test_invalid(self, kwargs, match):
        with pytest.raises(ValueError, match=match):
            LayerSpec(**kwargs)

    def test_auto_squash(self):
        assert [p[0] for p in SHADING.channel_plan()] == ["sigmoid"]  # identity 1 inside [0, 2]
        assert [p[0] for p in LIGHT.channel_plan()] == ["clamp"] * 3  # identity 0 on the boundary
        assert [p[0] for p in COLOR.channel_plan()] == ["sigmoid"] * 3 + ["clamp"]  # colour mid, alpha 0
        on_edge = LayerSpec(blend="multiply", channels=3, range=(0.0, 1.0))
        assert [p[0] for p in on_edge.channel_plan()] == ["clamp"] * 3


class TestIdentity:
    @pytest.mark.parametrize("name", PRESETS)
    def test_first_composite_is_the_input(self, name):
        spec = LayerSpec.from_preset(load_preset(LAYERS / name))
        u0 = spec.identity_preactivation().to(torch.float32).view(1, -1, 1, 1).expand(2, -1, 5, 7)
        base = torch.rand(2, 3, 5, 7, generator=torch.Generator().manual_seed(0))
        out = composite(base, activate(u0, spec), spec)
        assert (out - base).abs().max() <= 1e-5
        assert torch.equal(out, base)  # in fact exact for the three presets (multiplier 2·sigmoid(0) = 1)

    def test_identity_values(self):
        assert SHADING.identity_preactivation().tolist() == [0.0]
        assert LIGHT.identity_preactivation().tolist() == [0.0] * 3
        assert COLOR.identity_preactivation().tolist() == [0.0, 0.0, 0.0, 0.0]  # logit(0.5) ×3, alpha 0

    def test_forced_sigmoid_on_a_boundary_states_its_bound(self):
        spec = LayerSpec(blend="plus", channels=3, squash="sigmoid")
        u0 = spec.identity_preactivation()
        assert u0.tolist() == [-IDENTITY_LOGIT] * 3
        y = activate(u0.view(1, 3, 1, 1).float(), spec)
        bound = 1.0 / (1.0 + math.exp(IDENTITY_LOGIT))  # sigmoid(−12) = 6.1e-6
        assert torch.allclose(y, torch.full_like(y, bound), rtol=1e-5) and bound < 1e-5


class TestActivate:
    def test_sigmoid_range_reference(self):
        u = torch.linspace(-8, 8, 17, dtype=torch.float64).view(1, 1, 1, 17)
        y = activate(u, SHADING)
        ref = 2.0 / (1.0 + np.exp(-u.numpy()))
        np.testing.assert_allclose(y.numpy(), ref, rtol=1e-12)

    def test_clamp_exact_boundaries(self):
        u = torch.tensor([-0.5, 0.0, 0.3, 1.0, 1.7]).view(1, 1, 1, 5).repeat(1, 3, 1, 1)
        assert activate(u, LIGHT)[0, 0, 0].tolist() == pytest.approx([0.0, 0.0, 0.3, 1.0, 1.0])

    def test_wrong_channels(self):
        with pytest.raises(LasagnaError, match=r"expected \(B, 1, H, W\)"):
            activate(torch.zeros(1, 3, 2, 2), SHADING)

    @pytest.mark.parametrize("spec", [SHADING, COLOR, LIGHT], ids=["shading", "color", "light"])
    def test_inverse_roundtrip(self, spec):
        u = torch.rand(2, spec.channels, 3, 4, generator=torch.Generator().manual_seed(1)) * 4 - 2
        if spec is LIGHT:
            u = u.clamp(0, 1)
        if spec is COLOR:
            u[:, 3:] = u[:, 3:].clamp(0, 1)
        y = activate(u, spec)
        assert torch.allclose(activate(inverse(y, spec), spec), y, atol=1e-5)

    def test_inverse_refuses_out_of_range(self):
        with pytest.raises(LasagnaError, match=r"outside \[0.0, 2.0\]"):
            inverse(torch.full((1, 1, 1, 1), 2.5), SHADING)

    def test_nan_propagates(self):
        u = torch.tensor([[[[float("nan"), 0.0]]]])
        y = activate(u, SHADING)
        assert math.isnan(y[0, 0, 0, 0]) and y[0, 0, 0, 1] == 1.0


class TestClampInward:
    def test_forward_is_clamp(self):
        u = torch.linspace(-2, 3, 11)
        assert torch.equal(clamp_inward(u, 0.0, 1.0), u.clamp(0, 1))

    def test_gradient_inside_is_identity_float64(self):
        u = torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda x: clamp_inward(x, 0.0, 1.0), (u,))

    def test_gradient_outside_only_points_back(self):
        u = torch.tensor([-1.0, -1.0, 2.0, 2.0, 0.5], requires_grad=True)
        g = torch.tensor([-1.0, 1.0, -1.0, 1.0, 3.0])  # descent moves u by −g
        clamp_inward(u, 0.0, 1.0).backward(g)
        # below 0: keep g < 0 (u rises back); above 1: keep g > 0 (u falls back); inside: all of it
        assert u.grad.tolist() == [-1.0, 0.0, 0.0, 1.0, 3.0]

    def test_boundary_passes_gradient(self):
        u = torch.tensor([0.0, 1.0], requires_grad=True)
        clamp_inward(u, 0.0, 1.0).backward(torch.tensor([5.0, -5.0]))
        assert u.grad.tolist() == [5.0, -5.0]


class TestComposite:
    @pytest.mark.parametrize(
        "spec",
        [
            SHADING,
            COLOR,
            LIGHT,
            LayerSpec(blend="screen", channels=3),
            LayerSpec(blend="multiply", channels=3, range=(0.0, 2.0)),
        ],
        ids=["shading", "color", "light", "screen", "rgb-multiply"],
    )
    def test_reference_float64(self, spec):
        g = torch.Generator().manual_seed(3)
        base = torch.rand(2, 3, 4, 5, generator=g, dtype=torch.float64)
        layer = torch.rand(2, spec.channels, 4, 5, generator=g, dtype=torch.float64)
        layer[:, : spec.colour_channels] = (
            spec.range[0] + (spec.range[1] - spec.range[0]) * layer[:, : spec.colour_channels]
        )
        ref = np_composite(base.numpy(), layer.numpy(), spec.blend)  # a 1-channel layer broadcasts over RGB
        np.testing.assert_allclose(composite(base, layer, spec).numpy(), ref, rtol=1e-12, atol=1e-15)

    def test_split(self):
        layer = torch.rand(1, 4, 2, 2)
        colour, alpha = split(layer, COLOR)
        assert colour.shape == (1, 3, 2, 2) and alpha.shape == (1, 1, 2, 2)
        assert split(torch.rand(1, 1, 2, 2), SHADING)[1] is None

    def test_gradcheck_through_composite_float64(self):
        base = torch.rand(1, 3, 2, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
        u = (torch.rand(1, 4, 2, 3, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
        assert torch.autograd.gradcheck(lambda x: composite(base, activate(x, COLOR), COLOR), (u,))

    @given(st.floats(-30, 30), st.floats(0.0, 1.0))
    @settings(max_examples=40, deadline=None)
    def test_gradients_finite_everywhere(self, u_mult, alpha):
        """Finite gradients at multiplier 0 (sigmoid(−30)) and at α ∈ {0, 1} (boundaries of the clamp)."""
        base = torch.full((1, 3, 1, 1), 0.5)
        u = torch.tensor([[[[u_mult]]]], requires_grad=True)
        composite(base, activate(u, SHADING), SHADING).sum().backward()
        assert torch.isfinite(u.grad).all()
        v = torch.tensor([[[[0.2]], [[0.4]], [[0.6]], [[alpha]]]], requires_grad=True)
        composite(base, activate(v, COLOR), COLOR).sum().backward()
        assert torch.isfinite(v.grad).all()


def test_colour_over_luminance_keeps_the_base_luma_for_any_alpha():
    # Lum(Cb + α(SetLum(C, Lum(Cb)) − Cb)) = Lum(Cb): luma is linear and the colour carries the base's (float64).
    spec = LayerSpec(blend="normal", channels=4, luminance="base")
    rng = np.random.default_rng(7)
    base = torch.from_numpy(rng.random((2, 3, 9, 7)))
    layer = torch.from_numpy(rng.random((2, 4, 9, 7)))
    out = composite(base, layer, spec)
    w = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64).view(1, 3, 1, 1)
    torch.testing.assert_close((out * w).sum(1), (base * w).sum(1), atol=1e-12, rtol=0)
    assert float((out - base).abs().max()) > 0.1  # the colour did change
    free = composite(base, layer, LayerSpec(blend="normal", channels=4))
    assert float(((free - base) * w).sum(1).abs().max()) > 0.1  # a free layer's luma is its own


def test_colour_over_luminance_needs_normal_and_is_left_out_of_dumps_when_free():
    with pytest.raises(ValueError, match="expected blend normal"):
        LayerSpec(blend="multiply", channels=1, range=(0.0, 2.0), luminance="base")
    assert "luminance" not in LayerSpec(blend="normal", channels=4).model_dump()  # settings recorded before read alike
    assert LayerSpec(blend="normal", channels=4, luminance="base").model_dump()["luminance"] == "base"
    assert LayerSpec.from_preset(load_preset(Path("layers/color"))).luminance == "base"
