"""Photoshop's other modes (linear-burn … dissolve), kornia-style like the W3C ones: the shared ``_BlendTests``
per mode (smoke, shapes, exceptions, numpy float64 reference, in-place == pure, gradcheck, NaN), values at the
kinks against ``tests/compose/numpy_ref.py``'s ``PHOTOSHOP_B`` (psd-tools' formulas, pinned there against
Photoshop's renders; no code shared with ``lasagna.compose.blend``), Photoshop's partial alpha for
linear-dodge, the dissolve pattern, and the render path with both gradient engines.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.compose import backward
from lasagna.compose.blend import BLEND_FUNC, PHOTOSHOP_B, dissolve_pattern
from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import RenderLayerSpec
from lasagna.compose.render import render
from tests.compose import numpy_ref
from tests.compose.numpy_ref import FORMULAS
from tests.compose.test_blend import _BlendTests
from tests.compose.test_blend_modes import BG, CANVAS, kink_inputs, mode_stack

PHOTOSHOP = tuple(PHOTOSHOP_B)
# Cb = 0.5, Cs = 0.25 (gray), α = 0.5, by hand from the formulas: Co = 0.5 + 0.5·(B − 0.5).
HAND = {
    "linear-burn": 0.25,  # max(0, −0.25) = 0
    "linear-dodge": 0.625,  # 0.75
    "subtract": 0.375,  # 0.25
    "divide": 0.75,  # min(1, 2) = 1
    "vivid-light": 0.25,  # 1 − min(1, 0.5/0.5) = 0
    "linear-light": 0.25,  # max(0, 0.5 + 0.5 − 1) = 0
    "pin-light": 0.5,  # min(0.5, 0.5)
    "hard-mix": 0.25,  # 0.75 < 1: 0
    "darker-color": 0.375,  # Lum(Cs) < Lum(Cb): Cs
    "lighter-color": 0.5,  # Cb
    "dissolve": None,  # per pixel 0.5 or 0.25: tested on its own below
}


def _make(name: str) -> type:
    def test_reference_values(self):
        if HAND[name] is None:
            pytest.skip("dissolve's value is the pattern's: test_dissolve_*")
        out = self.fn(
            torch.full((3, 1, 1), 0.5, dtype=torch.float64),
            torch.full((1, 1, 1), 0.25, dtype=torch.float64),
            torch.full((1, 1, 1), 0.5, dtype=torch.float64),
        )
        torch.testing.assert_close(out, torch.full((3, 1, 1), HAND[name], dtype=torch.float64), rtol=0, atol=1e-15)

    cls_name = "Test" + "".join(p.capitalize() for p in name.split("-"))
    return type(cls_name, (_BlendTests,), {"name": name, "test_reference_values": test_reference_values})


for _name in PHOTOSHOP:
    _cls = _make(_name)
    globals()[_cls.__name__] = _cls
del _name, _cls


@pytest.mark.parametrize("name", PHOTOSHOP)
def test_values_at_the_kinks_match_photoshop(name):
    cb, cs, a = kink_inputs()
    expect = FORMULAS[name](cb.numpy(), cs.numpy(), a.numpy())
    np.testing.assert_allclose(BLEND_FUNC[name](cb, cs, a).numpy(), expect, rtol=0, atol=1e-12)
    if name != "dissolve":
        np.testing.assert_allclose(
            BLEND_FUNC[name](cb, cs, None).numpy(), numpy_ref.W3C_B[name](cb.numpy(), cs.numpy()), atol=1e-12
        )


@pytest.mark.parametrize("name", PHOTOSHOP)
@pytest.mark.parametrize("a_kind", ["tensor", "none"])
def test_gradients_finite_at_the_kinks(name, a_kind):
    cb, cs, a = (t.clone().requires_grad_() for t in kink_inputs())
    out = BLEND_FUNC[name](cb, cs, a if a_kind == "tensor" else None)
    w = torch.rand(out.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    leaves = (cb, cs, a) if a_kind == "tensor" else (cb, cs)
    for grad in torch.autograd.grad((out * w).sum(), leaves, allow_unused=True):
        assert grad is None or torch.isfinite(grad).all()


def test_vivid_light_poles_are_the_sources():
    # Unlike color-burn/-dodge (whose backdrop cases win), Photoshop's vivid light burns to 0 at Cs = 0 and
    # dodges to 1 at Cs = 1 whatever the backdrop (psd-tools #189).
    cb = torch.tensor([1.0, 0.0], dtype=torch.float64).view(1, 1, 2)
    cs = torch.tensor([0.0, 1.0], dtype=torch.float64).view(1, 1, 2)
    assert BLEND_FUNC["vivid-light"](cb, cs).flatten().tolist() == [0.0, 1.0]


def test_hard_mix_tie_goes_to_a_light_backdrop():
    cb = torch.tensor([100, 155, 128, 127], dtype=torch.float64).view(1, 1, 4) / 255.0
    cs = 1.0 - cb  # Cb + Cs = 1 exactly in float64
    assert BLEND_FUNC["hard-mix"](cb, cs).flatten().tolist() == [0.0, 1.0, 1.0, 0.0]


def test_linear_dodge_is_photoshops_not_w3c_plus_under_partial_alpha():
    # The 64/255: Cb = 0.75, Cs = 0.75, α = 0.5. Photoshop clamps inside the blend: 0.75 + 0.5·(1 − 0.75)
    # = 0.875; W3C plus clamps after it: min(1, 0.75 + 0.375) = 1.
    cb = torch.full((3, 1, 1), 0.75, dtype=torch.float64)
    cs = torch.full((3, 1, 1), 0.75, dtype=torch.float64)
    assert BLEND_FUNC["linear-dodge"](cb, cs, 0.5).flatten().tolist() == [0.875] * 3
    assert BLEND_FUNC["plus"](cb, cs, 0.5).clamp(0, 1).flatten().tolist() == [1.0] * 3
    # Where α ∈ {0, 1} the two agree.
    torch.testing.assert_close(BLEND_FUNC["linear-dodge"](cb, cs), BLEND_FUNC["plus"](cb, cs).clamp(0, 1))


def test_darker_and_lighter_color_pick_whole_pixels():
    cb = torch.tensor([0.9, 0.1, 0.1], dtype=torch.float64).view(3, 1, 1)  # Lum 0.338
    cs = torch.tensor([0.1, 0.5, 0.1], dtype=torch.float64).view(3, 1, 1)  # Lum 0.336
    assert torch.equal(BLEND_FUNC["darker-color"](cb, cs), cs)
    assert torch.equal(BLEND_FUNC["lighter-color"](cb, cs), cb)


# ---- dissolve --------------------------------------------------------------------------------------


def test_dissolve_pattern_is_the_documented_hash_and_uniform():
    u = dissolve_pattern(torch.arange(0, 256)[:, None], torch.arange(0, 256)[None]).numpy()
    np.testing.assert_array_equal(u, numpy_ref.dissolve_u(256, 256)[0])
    assert u.min() >= 0.0 and u.max() < 1.0
    hist = np.histogram(u, bins=16, range=(0, 1))[0] / u.size
    assert np.abs(hist - 1 / 16).max() < 0.01  # uniform within 1 % per sixteenth
    assert abs(np.corrcoef(u[:, :-1].ravel(), u[:, 1:].ravel())[0, 1]) < 0.02  # neighbours uncorrelated


def test_dissolve_shows_a_fraction_alpha_of_the_pixels_and_is_normal_when_opaque():
    cb = torch.zeros(3, 128, 128, dtype=torch.float64)
    cs = torch.ones(3, 128, 128, dtype=torch.float64)
    for a in (0.0, 0.3, 0.7, 1.0):
        out = BLEND_FUNC["dissolve"](cb, cs, a)
        assert set(out.unique().tolist()) <= {0.0, 1.0}
        assert float(out.mean()) == pytest.approx(a, abs=0.01)
    assert torch.equal(BLEND_FUNC["dissolve"](cb, cs), cs)


def test_dissolve_pattern_moves_with_the_layer_and_ignores_bands(monkeypatch):
    from lasagna.compose import engine

    g = torch.Generator().manual_seed(9)
    layers = [
        RenderLayerSpec(id="base", tensors=LayerTensors(torch.rand(3, 40, 30, generator=g))),
        RenderLayerSpec(
            id="d",
            blend="dissolve",
            offset=(3, 5),
            opacity=0.5,
            tensors=LayerTensors(torch.rand(3, 20, 20, generator=g), torch.rand(1, 20, 20, generator=g)),
        ),
    ]
    whole = render(layers, canvas=(40, 30)).image
    monkeypatch.setattr(engine, "TILE_PIXELS", 30 * 3)  # bands of 3 rows
    banded = render(layers, canvas=(40, 30)).image
    assert torch.equal(whole, banded)
    ref = numpy_ref.composite(layers, (40, 30))
    np.testing.assert_allclose(whole.double().numpy(), ref, atol=1e-6)


def test_dissolve_passes_no_gradient_to_alpha():
    cb = torch.rand(3, 4, 5, dtype=torch.float64)
    cs = torch.rand(3, 4, 5, dtype=torch.float64, requires_grad=True)
    a = torch.rand(1, 4, 5, dtype=torch.float64, requires_grad=True)
    ga, gs = torch.autograd.grad(BLEND_FUNC["dissolve"](cb, cs, a).sum(), (a, cs), allow_unused=True)
    assert torch.equal(ga, torch.zeros_like(a)) and gs is not None


# ---- the render path -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", PHOTOSHOP)
@pytest.mark.parametrize("blend_space", ["srgb", "linear"])
@pytest.mark.parametrize("clamp", ["layer", None])
def test_render_matches_reference(name, blend_space, clamp):
    layers = mode_stack(name, seed=1)
    ours = render(layers, canvas=CANVAS, background=BG, blend_space=blend_space, clamp=clamp).image
    ref = numpy_ref.composite(layers, CANVAS, BG, blend_space, clamp)
    np.testing.assert_allclose(ours.numpy(), ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", PHOTOSHOP)
def test_banded_backward_equals_autograd(name, monkeypatch):
    monkeypatch.setattr(backward, "BACKWARD_TILE_PIXELS", 14)  # bands of 2 rows
    layers = mode_stack(name, seed=2, requires_grad=True)
    op = torch.tensor(0.8, dtype=torch.float64, requires_grad=True)
    layers[2] = RenderLayerSpec(id="part", blend=name, offset=(2, 1), opacity=op, tensors=layers[2].tensors)
    leaves = [t for s in layers for t in s.tensors.tensors() if t is not None] + [op]
    weights = torch.rand(3, *CANVAS, dtype=torch.float64)
    grads = {}
    for engine in ("banded", "autograd"):
        image = render(layers, canvas=CANVAS, background=BG, grad_engine=engine).image
        grads[engine] = torch.autograd.grad((image * weights).sum(), leaves, allow_unused=True)
    for a, b in zip(grads["banded"], grads["autograd"]):
        zero = torch.zeros((), dtype=torch.float64)
        a = zero if a is None else a  # dissolve: no gradient reaches α (None on the banded engine, 0 on autograd)
        b = zero if b is None else b
        assert torch.isfinite(a).all()
        torch.testing.assert_close(
            a.expand_as(b) if a.ndim == 0 else a, b.expand_as(a) if b.ndim == 0 else b, rtol=1e-10, atol=1e-12
        )


@pytest.mark.parametrize("name", PHOTOSHOP)
def test_inplace_table_is_used_by_the_fast_path(name):
    layers = mode_stack(name, seed=4, dtype=torch.float32)
    fast = render(layers, canvas=CANVAS, background=BG).image
    learned = mode_stack(name, seed=4, dtype=torch.float32, requires_grad=True)
    slow = render(learned, canvas=CANVAS, background=BG, grad_engine="autograd").image
    assert torch.equal(fast, slow.detach())
