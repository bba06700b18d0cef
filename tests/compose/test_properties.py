"""Property tests over random stacks (up to 256 layers on canvases up to 8x8, offsets in and out of the
canvas, random opacities, visibility, blends, ranges, alphas, masks and no-op layers)."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lasagna.compose.blend import BLEND_MODES
from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import RenderLayerSpec, compile_plan
from lasagna.compose.render import half_precision_bound, render
from lasagna.compose.renderer import Renderer
from tests.compose import numpy_ref

# Deterministic examples: a property failure is reproducible in CI, never a flaky run.
SETTINGS = dict(
    deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large]
)

RANGES = {
    "normal": [(0.0, 1.0)],
    "screen": [(0.0, 1.0)],
    "multiply": [(0.0, 1.0), (0.0, 2.0)],
    "plus": [(0.0, 1.0), (-1.0, 1.0)],
}
RANGES.update({b: [(0.0, 1.0)] for b in BLEND_MODES if b not in RANGES})  # the other W3C modes: colours
# Precision properties (float32 and half vs float64, the half-precision bound) use the modes that are
# 1-Lipschitz in the backdrop, as that bound assumes (render.py), and do not amplify the rounding of
# their source: overlay and soft-light have slope up to 2 in Cb; color-dodge and color-burn divide by
# 1 − Cs and Cs (a gain up to 1/ulp near the pole), ClipColor by L − min and max − L.
ROUNDING_STABLE = ("normal", "multiply", "plus", "screen", "darken", "lighten", "hard-light", "difference", "exclusion")


@st.composite
def layer_recipe(draw, factors_above_one: bool = True, blends: tuple[str, ...] = BLEND_MODES):
    blend = draw(st.sampled_from(blends))
    ranges = RANGES[blend] if factors_above_one or blend != "multiply" else [(0.0, 1.0)]
    return dict(
        blend=blend,
        c=draw(st.sampled_from([1, 3])),
        h=draw(st.integers(1, 10)),
        w=draw(st.integers(1, 10)),
        x=draw(st.integers(-10, 9)),
        y=draw(st.integers(-10, 9)),
        opacity=draw(st.sampled_from([0.0, 1.0, 0.5]) | st.floats(0.0, 1.0)),
        visible=draw(st.sampled_from([True, True, True, False])),
        alpha=draw(st.sampled_from(["none", "none", "random", "zeros", "ones"])),
        mask=draw(st.sampled_from(["none", "none", "random", "ones"])),
        values=draw(st.sampled_from(["random", "random", "neutral", "edges"])),
        range=draw(st.sampled_from(ranges)),
    )


def stacks(max_small: int = 8, factors_above_one: bool = True, blends: tuple[str, ...] = BLEND_MODES):
    recipe = layer_recipe(factors_above_one, blends)
    return st.tuples(
        st.one_of(st.lists(recipe, max_size=max_small), st.lists(recipe, min_size=200, max_size=256)),
        st.integers(1, 8),
        st.integers(1, 8),
        st.integers(0, 2**31 - 1),
        st.tuples(*[st.sampled_from([0.0, 0.3, 1.0])] * 3),
    )


def build(recipes, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    layers = []
    for i, r in enumerate(recipes):
        lo, hi = r["range"]
        shape = (r["c"], r["h"], r["w"])
        if r["values"] == "neutral":
            color = torch.full(shape, {"multiply": 1.0}.get(r["blend"], 0.0), dtype=torch.float64)
        elif r["values"] == "edges":
            color = torch.tensor([lo, hi], dtype=torch.float64)[torch.randint(0, 2, shape, generator=g)]
        else:
            color = lo + (hi - lo) * torch.rand(shape, generator=g, dtype=torch.float64)
        extra = {}
        for name in ("alpha", "mask"):
            kind = r[name]
            size = (1, r["h"], r["w"])
            if kind == "none":
                extra[name] = None
            elif kind == "random":
                extra[name] = torch.rand(size, generator=g, dtype=torch.float64)
            else:
                extra[name] = torch.full(size, 0.0 if kind == "zeros" else 1.0, dtype=torch.float64)
        tensors = LayerTensors(color.to(dtype), *(None if t is None else t.to(dtype) for t in extra.values()))
        layers.append(
            RenderLayerSpec(
                id=f"l{i}",
                tensors=tensors,
                blend=r["blend"],
                opacity=r["opacity"],
                visible=r["visible"],
                offset=(r["x"], r["y"]),
                range=(lo, hi),
            )
        )
    return layers


@settings(max_examples=25, **SETTINGS)
@given(stacks(), st.sampled_from(["layer", "output"]), st.sampled_from(["srgb", "linear"]))
def test_matches_reference_finite_and_in_unit_range(stack, clamp, blend_space):
    recipes, h, w, seed, bg = stack
    layers = build(recipes, seed)
    image = render(layers, canvas=(h, w), background=bg, clamp=clamp, blend_space=blend_space).image
    assert image.shape == (3, h, w)
    assert torch.isfinite(image).all() and image.min() >= 0.0 and image.max() <= 1.0
    expect = numpy_ref.composite(layers, (h, w), bg, blend_space, clamp)
    np.testing.assert_allclose(image.numpy(), expect, atol=1e-9)


@settings(max_examples=25, **SETTINGS)
@given(stacks(), st.sampled_from(["layer", "output", None]))
def test_culling_never_changes_the_result(stack, clamp):
    recipes, h, w, seed, bg = stack
    layers = build(recipes, seed, torch.float32)
    culled = render(layers, canvas=(h, w), background=bg, clamp=clamp)
    full = render(layers, canvas=(h, w), background=bg, clamp=clamp, cull=False)
    assert (culled.image.double() - full.image.double()).abs().max() <= 1e-6
    assert set(culled.evaluated) <= set(full.evaluated)
    assert set(culled.skipped) | set(culled.evaluated) == {s.id for s in layers}
    for spec in layers:  # every skip reason is a true statement about the layer
        reason = culled.skipped.get(spec.id)
        if reason == "hidden":
            assert not spec.visible
        elif reason == "zero-opacity":
            assert spec.opacity == 0.0
        elif reason == "identity":
            assert spec.tensors.is_identity(spec.blend)


@settings(max_examples=25, **SETTINGS)
@given(stacks(blends=ROUNDING_STABLE), st.sampled_from(["srgb", "linear"]))
def test_float32_agrees_with_float64(stack, blend_space):
    recipes, h, w, seed, bg = stack
    plan = compile_plan(build(recipes, seed), (h, w), bg, blend_space)
    ref = render(plan).image
    assert (render(plan, dtype=torch.float32).image.double() - ref).abs().max() <= 1e-5


@settings(max_examples=25, **SETTINGS)
@given(stacks(factors_above_one=False, blends=ROUNDING_STABLE))
def test_half_precision_within_documented_bound(stack):
    recipes, h, w, seed, bg = stack
    plan = compile_plan(build(recipes, seed), (h, w), bg)
    ref = render(plan).image
    for dtype in (torch.float16, torch.bfloat16):
        err = (render(plan, dtype=dtype).image.double() - ref).abs().max().item()
        assert err <= half_precision_bound(dtype, len(plan.steps))


edit = st.tuples(st.integers(0, 11), st.sampled_from(["scale", "opacity", "visible", "offset", "replace", "nothing"]))


@settings(max_examples=40, **SETTINGS)
@given(stacks(max_small=12), st.lists(edit, min_size=1, max_size=8), st.integers(0, 3))
def test_prefix_cache_equals_a_fresh_render_after_random_edits(stack, edits, budget):
    recipes, h, w, seed, bg = stack
    layers = build(recipes, seed, torch.float32)
    renderer = Renderer((h, w), bg, cache_bytes=budget * 3 * h * w * 4)
    assert torch.equal(renderer.render(layers).image, render(layers, canvas=(h, w), background=bg).image)
    for i, kind in edits:
        if layers and kind != "nothing":
            i %= len(layers)
            s = layers[i]
            if kind == "scale":
                s.tensors.color.mul_(0.75)
            elif kind == "opacity":
                layers[i] = dataclasses.replace(s, opacity=1.0 - s.opacity)
            elif kind == "visible":
                layers[i] = dataclasses.replace(s, visible=not s.visible)
            elif kind == "offset":
                layers[i] = dataclasses.replace(s, offset=(s.offset[0] + 1, s.offset[1] - 1))
            else:
                layers[i] = dataclasses.replace(s, tensors=LayerTensors(s.tensors.color.clone() * 0.5, s.tensors.alpha))
        got = renderer.render(layers)
        expect = render(layers, canvas=(h, w), background=bg)
        assert torch.equal(got.image, expect.image)
        assert (got.skipped, got.evaluated) == (expect.skipped, expect.evaluated)


@settings(max_examples=20, **SETTINGS)
@given(
    stacks(),
    st.sampled_from(["layer", "output", None]),
    st.sampled_from(["srgb", "linear"]),
    st.sampled_from([0.0, 1.0]),
)
def test_gradients_finite_at_alpha_edges_and_zero_multipliers(stack, clamp, blend_space, edge):
    recipes, h, w, seed, bg = stack
    layers = build(recipes, seed)
    learned = torch.zeros(1, h, w, dtype=torch.float64, requires_grad=True)  # a multiplier of 0
    alpha = torch.full((1, h, w), edge, dtype=torch.float64, requires_grad=True)
    op = torch.tensor(edge, dtype=torch.float64, requires_grad=True)
    layers.insert(
        len(layers) // 2,
        RenderLayerSpec(id="learned", blend="multiply", opacity=op, tensors=LayerTensors(learned, alpha)),
    )
    result = render(layers, canvas=(h, w), background=bg, clamp=clamp, blend_space=blend_space)
    if "learned" in result.skipped:  # under an opaque layer: its true gradient is zero, none is computed
        assert result.skipped["learned"] == "occluded" and not result.image.requires_grad
        return
    image = result.image
    (image * torch.linspace(-1, 1, image.numel(), dtype=torch.float64).view_as(image)).sum().backward()
    for t in (learned, alpha, op):
        assert t.grad is not None and torch.isfinite(t.grad).all()
