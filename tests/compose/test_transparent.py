"""A canvas without a background (a transparent document): the composite carries alpha.

Against the independent float64 reference (``group_ref.composite_rgba``: the top level composited as an
isolated group's children, W3C Compositing Level 1, section 8.2) on random trees of every mode, groups, masks
and clipping chains; the banded no-grad engine against the recorded one; culling never changing a result;
gradients (gradcheck in float64); and an opaque base making the result the opaque render with alpha 1.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from lasagna.compose.blend import BLEND_MODES
from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import RenderLayerSpec, compile_plan
from lasagna.compose.render import render
from lasagna.errors import LasagnaError
from tests.compose import group_ref
from tests.compose.test_groups import CANVAS, UNBOUNDED_MODES, random_tree


def transparent_tree(seed: int, **kw):
    """``random_tree`` with its opaque base given partial alpha and a smaller rectangle: nothing covers the canvas."""
    specs = random_tree(seed, **kw)
    base = specs[0]
    h, w = CANVAS[0] - 2, CANVAS[1] - 3
    g = torch.Generator().manual_seed(seed)
    alpha = torch.rand(1, h, w, generator=g, dtype=torch.float64)
    specs[0] = dataclasses.replace(base, tensors=LayerTensors(base.tensors.color[:, :h, :w], alpha), offset=(1, 1))
    return specs


class TestReference:
    @pytest.mark.parametrize("seed", range(30))
    def test_random_trees_match_the_float64_reference(self, seed):
        specs = transparent_tree(seed)
        out = render(specs, canvas=CANVAS, background=None)
        color, alpha = group_ref.composite_rgba(specs, CANVAS)
        np.testing.assert_allclose(out.alpha.numpy(), alpha, atol=1e-9, rtol=0)
        # The straight colour is defined where alpha is not 0: compare premultiplied.
        np.testing.assert_allclose((out.image * out.alpha).numpy(), color * alpha, atol=1e-9, rtol=0)
        assert bool((out.image[:, (out.alpha[0] == 0)] == 0).all())

    @pytest.mark.parametrize("blend_space", ["srgb", "linear"])
    @pytest.mark.parametrize("clamp", ["layer", "output"])
    @pytest.mark.parametrize("seed", range(6))
    def test_blend_spaces_and_clamp_policies(self, seed, blend_space, clamp):
        specs = transparent_tree(200 + seed, modes=BLEND_MODES if clamp == "layer" else UNBOUNDED_MODES)
        kw = dict(blend_space=blend_space, clamp=clamp)
        out = render(specs, canvas=CANVAS, background=None, **kw)
        color, alpha = group_ref.composite_rgba(specs, CANVAS, **kw)
        seen = alpha[0] > 1e-6
        np.testing.assert_allclose(out.alpha.numpy(), alpha, atol=1e-9, rtol=0)
        np.testing.assert_allclose(out.image.numpy()[:, seen], color[:, seen], atol=1e-6, rtol=0)

    def test_two_half_transparent_layers_give_the_specs_worked_example(self):
        """W3C section 5.1: red α .5 then blue α .5 on transparency give αo = .75, Co = (1/3, 0, 2/3)."""

        def box(id, rgb):
            color = torch.tensor(rgb, dtype=torch.float64).view(3, 1, 1)
            return RenderLayerSpec(id=id, tensors=LayerTensors(color, torch.full((1, 1, 1), 0.5, dtype=torch.float64)))

        out = render([box("red", [1.0, 0, 0]), box("blue", [0, 0, 1.0])], canvas=(1, 1), background=None)
        assert out.alpha.item() == pytest.approx(0.75, abs=1e-15)
        assert out.image.flatten().tolist() == pytest.approx([1 / 3, 0.0, 2 / 3], abs=1e-15)


class TestEngines:
    @pytest.mark.parametrize("seed", range(10))
    def test_culling_never_changes_the_result(self, seed):
        specs = transparent_tree(300 + seed)
        a = render(specs, canvas=CANVAS, background=None)
        b = render(specs, canvas=CANVAS, background=None, cull=False)
        torch.testing.assert_close(a.image, b.image, atol=1e-12, rtol=0)
        torch.testing.assert_close(a.alpha, b.alpha, atol=1e-12, rtol=0)

    def test_bands_match_the_recorded_pass(self, monkeypatch):
        """The no-grad engine composites a few rows at a time; the recorded one the whole canvas."""
        import lasagna.compose.engine as engine

        specs = transparent_tree(7)
        whole = render(specs, canvas=CANVAS, background=None)
        monkeypatch.setattr(engine, "TILE_PIXELS", 2 * CANVAS[1])  # two rows a band
        banded = render(specs, canvas=CANVAS, background=None)
        torch.testing.assert_close(banded.image, whole.image, atol=0, rtol=0)
        torch.testing.assert_close(banded.alpha, whole.alpha, atol=0, rtol=0)

    def test_an_opaque_full_base_gives_the_opaque_render_and_alpha_one(self):
        specs = random_tree(11)  # its base is opaque and covers the canvas
        opaque = render(specs, canvas=CANVAS, background=(0.3, 0.3, 0.3))
        clear = render(specs, canvas=CANVAS, background=None)
        torch.testing.assert_close(clear.alpha, torch.ones_like(clear.alpha), atol=1e-12, rtol=0)
        torch.testing.assert_close(clear.image, opaque.image, atol=1e-9, rtol=0)
        assert opaque.alpha is None

    def test_gradcheck_through_a_transparent_canvas(self):
        g = torch.Generator().manual_seed(0)
        color = torch.rand(3, 3, 4, generator=g, dtype=torch.float64)
        alpha = torch.rand(1, 3, 4, generator=g, dtype=torch.float64)
        shade = (0.2 + torch.rand(1, 3, 4, generator=g, dtype=torch.float64)).requires_grad_()
        a_top = torch.rand(1, 3, 4, generator=g, dtype=torch.float64).requires_grad_()

        def f(shade, a_top):
            base = RenderLayerSpec(id="base", tensors=LayerTensors(color, alpha))
            top = RenderLayerSpec(id="s", tensors=LayerTensors(shade, a_top), blend="multiply", range=(0.0, 2.0))
            out = render([base, top], canvas=(3, 4), background=None, clamp="output")
            return out.image * out.alpha, out.alpha

        assert torch.autograd.gradcheck(f, (shade, a_top))

    def test_out_receives_the_colour(self):
        specs = transparent_tree(3)
        plan = compile_plan(specs, CANVAS, background=None)
        out = torch.empty(3, *CANVAS, dtype=torch.float64)
        result = render(plan, out=out)
        assert result.image.data_ptr() == out.data_ptr() and result.alpha is not None

    def test_a_background_of_two_numbers_is_refused_in_one_line(self):
        with pytest.raises(LasagnaError, match="or None"):
            compile_plan([], (2, 2), background=(0.1, 0.2))
