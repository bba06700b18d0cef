"""The W3C Compositing Level 1 modes beyond the first four, kornia-style: one class per op (the shared
``_BlendTests``: smoke, shapes, exceptions, numpy float64 reference, in-place == pure, gradcheck, NaN),
then the kinks (inputs exactly on them: values against the spec, finite gradients, the subgradients
chosen), invariants (hypothesis), and the render path in both blend spaces with both gradient engines.

The reference is ``tests/compose/numpy_ref.py``'s ``W3C_B``: numpy float64 from the spec's pseudo-code
(SetSat by sorting the channels), sharing no code with ``lasagna.compose.blend``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.compose import backward
from lasagna.compose.blend import BLEND_FUNC, BLEND_INPLACE, W3C_B
from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import RenderLayerSpec
from lasagna.compose.render import render
from tests.compose import numpy_ref
from tests.compose.numpy_ref import FORMULAS, NON_SEPARABLE
from tests.compose.test_blend import _BlendTests

W3C = tuple(W3C_B)  # the modes computed as lerp(Cb, B, α)
SEPARABLE = tuple(m for m in W3C if m not in NON_SEPARABLE)
# Cb = 0.5, Cs = 0.25 (gray), α = 0.5, by hand from the spec: Co = 0.5 + 0.5·(B − 0.5).
HAND = {
    "overlay": 0.375,  # Cb ≤ ½: 2·Cs·Cb = 0.25
    "darken": 0.375,
    "lighten": 0.5,
    "color-dodge": 0.5 + 0.5 * (0.5 / 0.75 - 0.5),
    "color-burn": 0.25,  # 1 − min(1, 0.5/0.25) = 0
    "hard-light": 0.375,  # Cs ≤ ½: Cb·2Cs = 0.25
    "soft-light": 0.5 + 0.5 * (-0.5 * 0.25),  # Cb − (1 − 2Cs)·Cb(1 − Cb) = 0.375
    "difference": 0.375,
    "exclusion": 0.5,  # 0.5 + 0.25 − 0.25
    "hue": 0.5,  # gray over gray: Lum(Cb)
    "saturation": 0.5,
    "color": 0.5,
    "luminosity": 0.375,  # Lum(Cs)
}


def _make(name: str) -> type:
    def test_reference_values(self):
        out = self.fn(
            torch.full((3, 1, 1), 0.5, dtype=torch.float64),
            torch.full((1, 1, 1), 0.25, dtype=torch.float64),
            torch.full((1, 1, 1), 0.5, dtype=torch.float64),
        )
        torch.testing.assert_close(out, torch.full((3, 1, 1), HAND[name], dtype=torch.float64), rtol=0, atol=1e-15)

    cls_name = "Test" + "".join(p.capitalize() for p in name.split("-"))
    return type(cls_name, (_BlendTests,), {"name": name, "test_reference_values": test_reference_values})


for _name in W3C:
    _cls = _make(_name)
    globals()[_cls.__name__] = _cls
del _name, _cls


# ---- the kinks ------------------------------------------------------------------------------------

EDGES = torch.tensor([0.0, 0.25, 0.5, 1.0], dtype=torch.float64)


def kink_inputs() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every pair (Cb, Cs) of the kink values 0, ¼, ½, 1 per channel (grays, ties, Cs = 1 with Cb = 0, …),
    plus random colours that need ClipColor (SetLum far out of gamut)."""
    cb, cs = torch.meshgrid(EDGES, EDGES, indexing="ij")  # (4, 4)
    cb = cb.reshape(1, 1, 16).expand(3, 1, 16)
    cs = cs.reshape(1, 1, 16).expand(3, 1, 16)
    g = torch.Generator().manual_seed(21)
    rnd = torch.rand(2, 3, 1, 16, generator=g, dtype=torch.float64)
    saturated = (torch.rand(2, 3, 1, 16, generator=g, dtype=torch.float64) > 0.5).double()  # 0/1 corners
    cb = torch.cat([cb, rnd[0], saturated[0], EDGES[torch.randint(0, 4, (3, 1, 16), generator=g)]], dim=-1)
    cs = torch.cat([cs, saturated[1], rnd[1], EDGES[torch.randint(0, 4, (3, 1, 16), generator=g)]], dim=-1)
    a = torch.rand(1, 1, cb.shape[-1], generator=g, dtype=torch.float64)
    return cb.contiguous(), cs.contiguous(), a


@pytest.mark.parametrize("name", W3C)
def test_values_at_the_kinks_match_the_spec(name):
    cb, cs, a = kink_inputs()
    expect = FORMULAS[name](cb.numpy(), cs.numpy(), a.numpy())
    np.testing.assert_allclose(BLEND_FUNC[name](cb, cs, a).numpy(), expect, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        BLEND_FUNC[name](cb, cs, None).numpy(), numpy_ref.W3C_B[name](cb.numpy(), cs.numpy()), atol=1e-12
    )


@pytest.mark.parametrize("name", W3C)
@pytest.mark.parametrize("a_kind", ["tensor", "none"])
def test_gradients_finite_at_the_kinks(name, a_kind):
    cb, cs, a = (t.clone().requires_grad_() for t in kink_inputs())
    out = BLEND_FUNC[name](cb, cs, a if a_kind == "tensor" else None)
    w = torch.rand(out.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    leaves = (cb, cs, a) if a_kind == "tensor" else (cb, cs)
    for grad in torch.autograd.grad((out * w).sum(), leaves):
        assert torch.isfinite(grad).all()


def _dB(name: str, cb: float, cs: float) -> tuple[float, float]:
    """(∂B/∂Cb, ∂B/∂Cs) of a gray pixel at exactly (cb, cs)."""
    cbt = torch.full((1, 1, 1), cb, dtype=torch.float64, requires_grad=True)
    cst = torch.full((1, 1, 1), cs, dtype=torch.float64, requires_grad=True)
    g = torch.autograd.grad(BLEND_FUNC[name](cbt, cst).sum(), (cbt, cst))
    return float(g[0]), float(g[1])


@pytest.mark.parametrize(
    "name, cb, cs, expect",
    [
        ("color-dodge", 0.5, 1.0, (0.0, 0.0)),  # saturated at 1: constant
        ("color-dodge", 0.0, 1.0, (0.0, 0.0)),  # the spec's Cb = 0 case wins
        ("color-dodge", 0.0, 0.5, (2.0, 0.0)),  # Cb = 0 below the pole: the quotient's slope 1/(1 − Cs)
        ("color-burn", 0.5, 0.0, (0.0, 0.0)),
        ("color-burn", 1.0, 0.0, (0.0, 0.0)),
        ("hard-light", 0.3, 0.5, (1.0, 0.6)),  # the ≤ ½ branch: ∂/∂Cs (2·Cs·Cb) = 2Cb
        ("overlay", 0.5, 0.3, (0.6, 1.0)),
        ("soft-light", 0.25, 1.0, (2.0, 0.5)),  # D is C¹ at ¼ (D' = 1): 1 + (2Cs − 1)(D' − 1) = 1; ∂Cs = 2(D − Cb)
        ("soft-light", 0.0, 1.0, (4.0, 0.0)),  # the polynomial at 0, never √'s infinite slope
        ("darken", 0.4, 0.4, (0.5, 0.5)),  # ties split evenly (torch.minimum)
        ("lighten", 0.4, 0.4, (0.5, 0.5)),
        ("difference", 0.4, 0.4, (0.0, 0.0)),  # abs'(0) = 0
    ],
)
def test_subgradients_chosen_at_the_kinks(name, cb, cs, expect):
    got = _dB(name, cb, cs)
    if name == "soft-light" and cb == 0.25:
        expect = (1.0, 2.0 * (0.5 - 0.25))
    assert got == pytest.approx(expect, abs=1e-12)


def test_gray_subgradient_of_set_sat_and_clip_color_is_finite():
    # All three channels equal: SetSat divides 0 by 1, ClipColor's guards hold (CLIP_COLOR_EPS).
    for name in NON_SEPARABLE:
        for v in (0.0, 0.5, 1.0, -0.25, 1.5):
            cb = torch.full((3, 1, 1), v, dtype=torch.float64, requires_grad=True)
            cs = torch.tensor([0.9, 0.1, 0.4], dtype=torch.float64).view(3, 1, 1).requires_grad_()
            out = BLEND_FUNC[name](cb, cs)
            assert torch.isfinite(out).all()
            for g in torch.autograd.grad(out.sum(), (cb, cs)):
                assert torch.isfinite(g).all()


@pytest.mark.parametrize("name", W3C)
def test_gradcheck_near_the_kinks(name):
    # Just off each kink (both sides, random distances), gradcheck in float64: the one-sided derivatives.
    g = torch.Generator().manual_seed(8)
    n = 48
    near = EDGES[torch.randint(0, 4, (2, 3, 1, n), generator=g)]
    step = (torch.rand(2, 3, 1, n, generator=g, dtype=torch.float64) * 3e-2 + 1e-2) * torch.where(
        torch.rand(2, 3, 1, n, generator=g) < 0.5, -1.0, 1.0
    ).double()
    x = near + step
    cb, cs = torch.where((x < 0) | (x > 1), near - step, x).clone()  # reflected into [0, 1], off the kinks
    a = torch.full((1, 1, n), 0.7, dtype=torch.float64)
    assert torch.autograd.gradcheck(BLEND_FUNC[name], (cb.requires_grad_(), cs.requires_grad_(), a.requires_grad_()))


# ---- invariants ------------------------------------------------------------------------------------

unit = st.floats(0.0, 1.0, allow_nan=False)
rgb = st.tuples(unit, unit, unit)


def px(c) -> torch.Tensor:
    return torch.tensor(c, dtype=torch.float64).view(-1, 1, 1)


def B(name: str, cb, cs) -> torch.Tensor:
    return BLEND_FUNC[name](px(cb), px(cs), None)


def lum(c: torch.Tensor) -> float:
    return float(0.3 * c[0] + 0.59 * c[1] + 0.11 * c[2])


@settings(max_examples=200, deadline=None, derandomize=True)
@given(rgb, rgb)
def test_separable_invariants(cb, cs):
    assert torch.equal(B("darken", cb, cb), px(cb)) and torch.equal(B("lighten", cb, cb), px(cb))
    assert torch.equal(B("difference", cb, (0.0, 0.0, 0.0)), px(cb))
    assert torch.equal(B("exclusion", cb, (0.0, 0.0, 0.0)), px(cb))
    assert torch.equal(B("overlay", cb, cs), B("hard-light", cs, cb))  # overlay is hard-light, commuted
    assert torch.equal(B("difference", cb, cs), B("difference", cs, cb))
    assert torch.equal(B("color-dodge", cb, (0.0, 0.0, 0.0)), px(cb))  # Cb / 1
    assert torch.allclose(B("color-burn", cb, (1.0, 1.0, 1.0)), px(cb), atol=2**-53)  # 1 − (1 − Cb), rounded
    assert torch.allclose(B("soft-light", cb, (0.5, 0.5, 0.5)), px(cb), atol=1e-15)
    for name in SEPARABLE:
        out = B(name, cb, cs)
        assert bool(((out >= -1e-15) & (out <= 1 + 1e-15)).all()), name


@settings(max_examples=200, deadline=None, derandomize=True)
@given(rgb, rgb)
def test_non_separable_invariants(cb, cs):
    color, lumi = B("color", cb, cs), B("luminosity", cb, cs)
    # color and luminosity are complementary: each is the other with backdrop and source swapped ...
    assert torch.equal(color, B("luminosity", cs, cb)) and torch.equal(lumi, B("color", cs, cb))
    # ... color keeps the backdrop's luminosity, luminosity takes the source's (ClipColor preserves Lum).
    assert lum(color) == pytest.approx(lum(px(cb)), abs=1e-6)
    assert lum(lumi) == pytest.approx(lum(px(cs)), abs=1e-6)
    for name in ("hue", "saturation"):
        assert lum(B(name, cb, cs)) == pytest.approx(lum(px(cb)), abs=1e-6)
    assert torch.allclose(B("saturation", cb, cb), px(cb), atol=1e-12)  # its own saturation: unchanged
    assert torch.allclose(B("hue", cb, cb), px(cb), atol=1e-12)
    for name in NON_SEPARABLE:
        out = B(name, cb, cs)
        assert bool(((out >= -1e-12) & (out <= 1 + 1e-12)).all()), name


# ---- the render path -------------------------------------------------------------------------------

CANVAS = (5, 7)
BG = (0.3, 0.6, 0.2)


def mode_stack(name: str, seed: int = 0, dtype=torch.float64, requires_grad: bool = False):
    """A base, then the mode three times: opaque over the canvas, with alpha and a mask at an offset,
    and a 1-channel source at opacity 0.6 — with exact kink values mixed in."""
    g = torch.Generator().manual_seed(seed)

    def r(*shape, kinks=True):
        x = torch.rand(*shape, generator=g, dtype=torch.float64)
        if kinks:
            pick = torch.rand(*shape, generator=g) < 0.3
            x = torch.where(pick, EDGES[torch.randint(0, 4, shape, generator=g)], x)
        return x.to(dtype).requires_grad_(requires_grad)

    return [
        RenderLayerSpec(id="base", tensors=LayerTensors(r(3, *CANVAS))),
        RenderLayerSpec(id="full", blend=name, tensors=LayerTensors(r(3, *CANVAS))),
        RenderLayerSpec(id="part", blend=name, offset=(2, 1), tensors=LayerTensors(r(3, 3, 4), r(1, 3, 4), r(1, 3, 4))),
        RenderLayerSpec(id="gray", blend=name, opacity=0.6, offset=(-1, 0), tensors=LayerTensors(r(1, 4, 6))),
    ]


@pytest.mark.parametrize("name", W3C)
@pytest.mark.parametrize("blend_space", ["srgb", "linear"])
@pytest.mark.parametrize("clamp", ["layer", None])
def test_render_matches_reference(name, blend_space, clamp):
    layers = mode_stack(name, seed=1)
    ours = render(layers, canvas=CANVAS, background=BG, blend_space=blend_space, clamp=clamp).image
    ref = numpy_ref.composite(layers, CANVAS, BG, blend_space, clamp)
    np.testing.assert_allclose(ours.numpy(), ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", W3C)
@pytest.mark.parametrize("blend_space", ["srgb", "linear"])
def test_banded_backward_equals_autograd(name, blend_space, monkeypatch):
    monkeypatch.setattr(backward, "BACKWARD_TILE_PIXELS", 14)  # bands of 2 rows
    layers = mode_stack(name, seed=2, requires_grad=True)
    op = torch.tensor(0.8, dtype=torch.float64, requires_grad=True)
    layers[2] = RenderLayerSpec(id="part", blend=name, offset=(2, 1), opacity=op, tensors=layers[2].tensors)
    leaves = [t for s in layers for t in s.tensors.tensors() if t is not None] + [op]
    weights = torch.rand(3, *CANVAS, dtype=torch.float64)
    grads = {}
    for engine in ("banded", "autograd"):
        image = render(layers, canvas=CANVAS, background=BG, blend_space=blend_space, grad_engine=engine).image
        grads[engine] = torch.autograd.grad((image * weights).sum(), leaves, allow_unused=True)
    for a, b in zip(grads["banded"], grads["autograd"]):
        assert (a is None) == (b is None)
        if a is not None:
            assert torch.isfinite(a).all()
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("name", W3C)
def test_gradcheck_whole_render_banded(name):
    g = torch.Generator().manual_seed(5)
    base = torch.rand(3, 2, 3, generator=g, dtype=torch.float64).requires_grad_()
    top = (torch.rand(3, 2, 3, generator=g, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()
    alpha = (torch.rand(1, 2, 3, generator=g, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()

    def f(base, top, alpha):
        layers = [
            RenderLayerSpec(id="base", tensors=LayerTensors(base)),
            RenderLayerSpec(id="top", blend=name, tensors=LayerTensors(top, alpha)),
        ]
        return render(layers, canvas=(2, 3), clamp=None).image

    assert torch.autograd.gradcheck(f, (base, top, alpha))


@pytest.mark.parametrize("name", W3C)
def test_inplace_table_is_used_by_the_fast_path(name):
    # The no-grad engine (in-place kernels, bands) equals the pure functions (autograd engine).
    layers = mode_stack(name, seed=4, dtype=torch.float32)
    fast = render(layers, canvas=CANVAS, background=BG).image
    learned = mode_stack(name, seed=4, dtype=torch.float32, requires_grad=True)
    slow = render(learned, canvas=CANVAS, background=BG, grad_engine="autograd").image
    assert torch.equal(fast, slow.detach())
    assert BLEND_INPLACE[name] is not BLEND_FUNC[name]
