"""The fused (compiled) W3C kernels of ``lasagna.compose.fused``.

Fused renders are checked against the float64 reference of the spec (``numpy_ref``) on the stacks of
``test_blend_modes`` (an opaque full-canvas layer, one with alpha and a mask at an offset, a 1-channel one at
opacity 0.6, kink values mixed in), and against the eager kernels in float32. Compiling takes about a
second per mode and variant with a warm inductor cache (ten with a cold one), so the default suite compiles two
modes in all (overlay and soft-light); ``-m slow`` compiles all thirteen in both blend spaces.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from lasagna.compose import fused, render, set_fused
from lasagna.compose.blend import W3C_B
from tests.compose import numpy_ref
from tests.compose.test_blend_modes import BG, CANVAS, mode_stack

# The default suite compiles one mode per test (cold inductor cache: ~10 s for overlay, ~12 s for hue).
SPEC_QUICK, F32_QUICK = "overlay", "soft-light"


def modes(quick: str) -> list:
    return [m if m == quick else pytest.param(m, marks=pytest.mark.slow) for m in W3C_B]


# Inductor builds the kernels with a C++ compiler found at run time (.ci/run installs g++).
needs_compiler = pytest.mark.skipif(
    not any(shutil.which(c) for c in ("g++", "c++", "clang++")), reason="no C++ compiler for torch.compile"
)


@pytest.fixture
def fused_on():
    set_fused(True)
    yield
    set_fused(False)
    fused._failed.clear()


@needs_compiler
@pytest.mark.parametrize("name", modes(SPEC_QUICK))
@pytest.mark.parametrize("blend_space", ["srgb", pytest.param("linear", marks=pytest.mark.slow)])
def test_fused_render_matches_the_spec_in_float64(name, blend_space, fused_on):
    layers = mode_stack(name, seed=1)
    ours = render(layers, canvas=CANVAS, background=BG, blend_space=blend_space).image
    assert name in fused._compiled and name not in fused._failed  # the compiled kernel ran
    ref = numpy_ref.composite(layers, CANVAS, BG, blend_space, "layer")
    np.testing.assert_allclose(ours.numpy(), ref, rtol=0, atol=1e-12)


@needs_compiler
@pytest.mark.parametrize("name", modes(F32_QUICK))
def test_fused_float32_within_two_ulp_of_eager(name, fused_on):
    layers = mode_stack(name, seed=3, dtype=torch.float32)
    canvas = CANVAS
    fast = render(layers, canvas=canvas, background=BG).image
    set_fused(False)
    eager = render(layers, canvas=canvas, background=BG).image
    # Inductor may contract a·b + c into one fused multiply-add: a rounding or two apart, no more.
    torch.testing.assert_close(fast, eager, rtol=0, atol=2 * torch.finfo(torch.float32).eps)


@needs_compiler
def test_fused_bands_and_batches(fused_on, monkeypatch):
    """Bands of a few rows (the last one shorter) and a batch dimension reuse one compiled graph."""
    from lasagna.compose import LayerTensors, RenderLayerSpec, engine

    monkeypatch.setattr(engine, "TILE_PIXELS", 3 * 11)  # 3 rows of 11 per band, 13 rows
    g = torch.Generator().manual_seed(4)
    base = RenderLayerSpec(id="b", tensors=LayerTensors(torch.rand(2, 3, 13, 11, generator=g, dtype=torch.float64)))
    top = RenderLayerSpec(
        id="t",
        blend="overlay",
        tensors=LayerTensors(torch.rand(2, 3, 13, 11, generator=g, dtype=torch.float64)),
        opacity=0.7,
    )
    ours = render([base, top], canvas=(13, 11)).image
    set_fused(False)
    eager = render([base, top], canvas=(13, 11)).image
    torch.testing.assert_close(ours, eager, rtol=0, atol=1e-15)


def test_fused_off_by_default_and_env(monkeypatch):
    monkeypatch.setattr(fused, "_state", {"enabled": None})
    monkeypatch.delenv(fused.ENV, raising=False)
    assert not fused.fused_enabled() and fused.fused_inplace("overlay") is None
    for value, on in (("1", True), ("yes", True), ("0", False), ("", False)):
        monkeypatch.setattr(fused, "_state", {"enabled": None})
        monkeypatch.setenv(fused.ENV, value)
        assert fused.fused_enabled() is on
    monkeypatch.setattr(fused, "_state", {"enabled": None})
    assert fused.fused_inplace("multiply") is None  # the basic modes are never compiled


def test_compile_failure_warns_once_and_falls_back(fused_on, monkeypatch):
    def broken(blend):
        raise RuntimeError("no C++ compiler found\nlong trace")

    monkeypatch.setattr(fused, "_make", broken)
    monkeypatch.setattr(fused, "_compiled", {})
    monkeypatch.setattr(fused, "_wrappers", {})
    layers = mode_stack("color-dodge", seed=5)
    with pytest.warns(RuntimeWarning, match=r"fused kernel for blend 'color-dodge' could not be compiled .*no C\+\+"):
        ours = render(layers, canvas=CANVAS, background=BG).image
    assert "color-dodge" in fused._failed and fused.fused_inplace("color-dodge") is None
    ref = numpy_ref.composite(layers, CANVAS, BG, "srgb", "layer")
    np.testing.assert_allclose(ours.numpy(), ref, rtol=0, atol=1e-12)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        render(layers, canvas=CANVAS, background=BG)  # no second warning
