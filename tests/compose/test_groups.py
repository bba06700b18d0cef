"""Groups in the compositor: isolated and pass-through, nested, against an independent float64 reference.

Random trees hold every blend mode, masks, offsets, partial alpha and nested groups; the reference is
``group_ref.py`` (numpy, the W3C formulas in non-premultiplied form). Also: the spec's own worked example,
culling never changing a result, the fast and recorded engines agreeing, gradients (gradcheck in float64
through an isolated group, banded == autograd) and the prefix-cache Renderer after edits inside a group.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from lasagna.compose.blend import BLEND_MODES
from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import RenderGroupSpec, RenderLayerSpec, compile_plan
from lasagna.compose.render import render
from lasagna.compose.renderer import Renderer
from lasagna.errors import LasagnaError
from tests.compose import group_ref

CANVAS = (9, 11)


# Modes whose formula is defined for values outside [0, 1] (clamp="output" keeps intermediates unclamped;
# soft-light's √Cb and the dodge/burn quotients are not, and implementations differ there).
UNBOUNDED_MODES = ("normal", "multiply", "screen", "plus", "darken", "lighten", "difference", "exclusion")


def random_tree(seed: int, depth: int = 3, dtype=torch.float64, n: int = 4, modes=BLEND_MODES):
    """Bottom-to-top specs: an opaque base, then layers and groups of every kind and of ``modes``."""
    g = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    counter = iter(range(10_000))

    def r(*shape):
        return torch.rand(*shape, generator=g, dtype=dtype)

    def leaf():
        blend = str(rng.choice(modes))
        h, w = int(rng.integers(2, 8)), int(rng.integers(2, 9))
        ranged = blend in ("multiply", "plus") and rng.random() < 0.5
        ch = 1 if blend == "multiply" and rng.random() < 0.5 else 3
        color = r(ch, h, w) * (2.0 if ranged else 1.0)
        alpha = r(1, h, w) if rng.random() < 0.6 else None
        mask = r(1, h, w) if rng.random() < 0.3 else None
        return RenderLayerSpec(
            id=f"l{next(counter)}",
            tensors=LayerTensors(color, alpha, mask),
            blend=blend,
            opacity=float(rng.choice([1.0, rng.random()])),
            offset=(int(rng.integers(-3, 8)), int(rng.integers(-3, 7))),
            range=(0.0, 2.0) if ranged else (0.0, 1.0),
            visible=bool(rng.random() > 0.1),
        )

    def group(d):
        isolated = bool(rng.random() < 0.5)
        kids = [group(d - 1) if d > 0 and rng.random() < 0.35 else leaf() for _ in range(int(rng.integers(1, n)))]
        mask = None
        if rng.random() < 0.4:
            mask = r(1, int(rng.integers(3, 10)), int(rng.integers(3, 12)))
        return RenderGroupSpec(
            id=f"g{next(counter)}",
            children=tuple(kids),
            isolated=isolated,
            blend=str(rng.choice(modes)) if isolated else "normal",
            opacity=float(rng.choice([1.0, 1.0, rng.random()])),
            offset=(int(rng.integers(-2, 3)), int(rng.integers(-2, 3))),
            mask=mask,
            visible=bool(rng.random() > 0.1),
        )

    base = RenderLayerSpec(id="base", tensors=LayerTensors(r(3, *CANVAS)))
    return [base] + [group(depth) if rng.random() < 0.6 else leaf() for _ in range(n)]


def reference(specs, **kw):
    return group_ref.composite(specs, CANVAS, **kw)


class TestReference:
    @pytest.mark.parametrize("seed", range(40))
    def test_random_nested_trees_match_the_float64_reference(self, seed):
        specs = random_tree(seed)
        got = render(specs, canvas=CANVAS, background=(0.2, 0.4, 0.6)).image.numpy()
        np.testing.assert_allclose(got, reference(specs, background=(0.2, 0.4, 0.6)), atol=1e-9, rtol=0)

    @pytest.mark.parametrize("blend_space", ["srgb", "linear"])
    @pytest.mark.parametrize("clamp", ["layer", "output"])
    @pytest.mark.parametrize("seed", range(8))
    def test_blend_spaces_and_clamp_policies(self, seed, blend_space, clamp):
        specs = random_tree(100 + seed, modes=BLEND_MODES if clamp == "layer" else UNBOUNDED_MODES)
        kw = dict(blend_space=blend_space, clamp=clamp)
        got = render(specs, canvas=CANVAS, **kw).image.numpy()
        np.testing.assert_allclose(got, reference(specs, **kw), atol=1e-9, rtol=0)

    def test_the_specs_worked_example_in_an_isolated_group(self):
        """W3C section 5.1, "both shape and backdrop transparent": red α .5 then blue α .5 give αo = .75 and
        Co = (1/3, 0, 2/3); the isolated group composited normally over black gives αo·Co = (.25, 0, .5)."""

        def box(id, rgb):
            color = torch.tensor(rgb, dtype=torch.float64).view(3, 1, 1)
            return RenderLayerSpec(id=id, tensors=LayerTensors(color, torch.full((1, 1, 1), 0.5)))

        group = RenderGroupSpec(id="g", isolated=True, children=(box("red", [1.0, 0, 0]), box("blue", [0, 0, 1.0])))
        got = render([group], canvas=(1, 1)).image.flatten().tolist()
        assert got == pytest.approx([0.25, 0.0, 0.5], abs=1e-15)

    def test_a_multiply_layer_over_transparency_paints_its_colour(self):
        """Over a transparent backdrop Cr = (1 − αb)·Cs + αb·B = Cs: a multiply by white is no identity there."""
        ones = torch.ones(3, 2, 2, dtype=torch.float64)
        white = RenderLayerSpec(id="w", blend="multiply", tensors=LayerTensors(ones))
        group = RenderGroupSpec(id="g", isolated=True, children=(white,))
        for cull in (True, False):
            out = render([group], canvas=(2, 2), background=(0.2, 0.2, 0.2), cull=cull)
            assert torch.equal(out.image, torch.ones(3, 2, 2, dtype=torch.float64))
        passing = RenderGroupSpec(id="g", children=(white,), opacity=0.5)
        assert render([passing], canvas=(2, 2), background=(0.2, 0.2, 0.2)).skipped == {"w": "identity", "g": "empty"}

    def test_an_isolated_normal_group_of_opaque_layers_is_the_top_one(self):
        a, b = (RenderLayerSpec(id=i, tensors=LayerTensors(torch.rand(3, 4, 4, dtype=torch.float64))) for i in "ab")
        group = RenderGroupSpec(id="g", isolated=True, children=(a, b))
        out = render([group], canvas=(4, 4))
        assert torch.allclose(out.image, b.tensors.color, atol=1e-15, rtol=0)
        assert out.skipped == {"a": "occluded"} and out.evaluated == ["g", "b"]

    def test_a_pass_through_group_of_opacity_one_is_its_children(self):
        specs = random_tree(7)
        flat = [specs[0]]
        for s in specs[1:]:
            flat.append(dataclasses.replace(s, opacity=1.0) if isinstance(s, RenderGroupSpec) and not s.isolated else s)
        plan = compile_plan(flat, CANVAS)
        assert not any(isinstance(s, RenderGroupSpec) and s.inlined for s in plan.layers)
        np.testing.assert_allclose(render(plan).image.numpy(), reference(flat), atol=1e-9, rtol=0)


class TestEngines:
    @pytest.mark.parametrize("seed", range(10))
    def test_culling_never_changes_the_result(self, seed):
        specs = random_tree(200 + seed)
        a = render(specs, canvas=CANVAS).image
        b = render(specs, canvas=CANVAS, cull=False).image
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)

    @pytest.mark.parametrize("seed", range(6))
    def test_fast_and_recorded_engines_agree(self, seed):
        specs = random_tree(300 + seed)
        fast = render(specs, canvas=CANVAS).image
        learn = specs[-1]
        if isinstance(learn, RenderGroupSpec):
            learn = dataclasses.replace(learn, opacity=torch.tensor(0.7, dtype=torch.float64, requires_grad=True))
        else:
            learn = dataclasses.replace(learn, opacity=torch.tensor(0.7, dtype=torch.float64, requires_grad=True))
        fixed = [*specs[:-1], dataclasses.replace(specs[-1], opacity=0.7)]
        recorded = render([*specs[:-1], learn], canvas=CANVAS).image
        torch.testing.assert_close(recorded.detach(), render(fixed, canvas=CANVAS).image, atol=1e-12, rtol=0)
        assert fast.shape == recorded.shape

    def test_batched_children_broadcast(self):
        base = RenderLayerSpec(id="base", tensors=LayerTensors(torch.rand(3, 4, 4, dtype=torch.float64)))
        batched = torch.rand(2, 3, 4, 4, dtype=torch.float64)
        kid = RenderLayerSpec(id="k", blend="overlay", tensors=LayerTensors(batched))
        group = RenderGroupSpec(id="g", isolated=True, blend="screen", children=(kid,), opacity=0.5)
        out = render([base, group], canvas=(4, 4)).image
        assert out.shape == (2, 3, 4, 4)
        for i in range(2):
            one = dataclasses.replace(kid, tensors=LayerTensors(kid.tensors.color[i]))
            single = render([base, dataclasses.replace(group, children=(one,))], canvas=(4, 4)).image
            torch.testing.assert_close(out[i], single, atol=1e-12, rtol=0)


class TestGradients:
    def _inputs(self):
        g = torch.Generator().manual_seed(5)

        def r(*s):
            return (torch.rand(*s, generator=g, dtype=torch.float64) * 0.8 + 0.1).requires_grad_()

        opacity = torch.tensor(0.6, dtype=torch.float64, requires_grad=True)
        return r(3, 4, 5), r(3, 3, 4), r(1, 3, 4), r(1, 4, 5), opacity

    def _render(self, base, color, alpha, mask, opacity, blend="overlay", inner="soft-light", engine="banded"):
        kid = RenderLayerSpec(id="k", blend=inner, offset=(1, 1), tensors=LayerTensors(color, alpha))
        under = RenderLayerSpec(id="u", tensors=LayerTensors(base * 0.5, base[:1] * 0.7))
        group = RenderGroupSpec(id="g", isolated=True, blend=blend, children=(under, kid), opacity=opacity, mask=mask)
        passing = RenderGroupSpec(id="p", children=(group,), opacity=0.8)
        base_spec = RenderLayerSpec(id="base", tensors=LayerTensors(base))
        return render([base_spec, passing], canvas=(4, 5), clamp=None, grad_engine=engine).image

    @pytest.mark.parametrize(("blend", "inner"), [("overlay", "soft-light"), ("normal", "multiply"), ("hue", "plus")])
    def test_gradcheck_through_an_isolated_group(self, blend, inner):
        assert torch.autograd.gradcheck(lambda *x: self._render(*x, blend=blend, inner=inner), self._inputs())

    def test_banded_request_equals_autograd(self):
        x = self._inputs()
        ga = torch.autograd.grad(self._render(*x, engine="autograd").sum(), x)
        gb = torch.autograd.grad(self._render(*x, engine="banded").sum(), x)
        for a, b in zip(ga, gb):
            torch.testing.assert_close(a, b, atol=1e-12, rtol=0)

    def test_a_transparent_group_pixel_has_finite_gradients(self):
        color = torch.rand(3, 2, 2, dtype=torch.float64, requires_grad=True)
        alpha = torch.zeros(1, 2, 2, dtype=torch.float64, requires_grad=True)
        kid = RenderLayerSpec(id="k", tensors=LayerTensors(color, alpha))
        group = RenderGroupSpec(id="g", isolated=True, blend="color-dodge", children=(kid,))
        out = render([group], canvas=(2, 2), background=(0.3, 0.3, 0.3)).image
        out.sum().backward()
        assert torch.isfinite(color.grad).all() and torch.isfinite(alpha.grad).all()


class TestRenderer:
    def test_editing_a_child_in_place_invalidates_the_group(self):
        specs = random_tree(11, depth=2)
        r = Renderer(CANVAS)
        r.render(specs)
        groups = [i for i, s in enumerate(specs) if isinstance(s, RenderGroupSpec) and not s.inlined]
        assert groups, "the tree has a group that is one step"
        i = groups[-1]

        def leaves(s):
            return [x for c in s.children for x in leaves(c)] if isinstance(s, RenderGroupSpec) else [s]

        for leaf in leaves(specs[i]):
            leaf.tensors.color.mul_(0.5)
            got = r.render(specs).image
            torch.testing.assert_close(got, render(specs, canvas=CANVAS).image, atol=0, rtol=0)
        assert r.last_restart <= i

    def test_editing_above_a_group_restarts_above_it(self):
        base = RenderLayerSpec(id="base", tensors=LayerTensors(torch.rand(3, *CANVAS)))
        kid = RenderLayerSpec(id="k", blend="difference", tensors=LayerTensors(torch.rand(3, 4, 4)))
        group = RenderGroupSpec(id="g", isolated=True, blend="multiply", children=(kid,), opacity=0.5)
        top = RenderLayerSpec(id="top", blend="screen", tensors=LayerTensors(torch.rand(3, *CANVAS)))
        specs = [base, group, top]
        r = Renderer(CANVAS)
        r.render(specs)
        top.tensors.color.mul_(0.5)
        got = r.render(specs).image
        assert r.last_recomputed == ["top"]
        assert torch.equal(got, render(specs, canvas=CANVAS).image)
        for opacity in (0.25, 0.75):  # the first edit of a layer takes the snapshot below it, the second uses it
            specs[1] = dataclasses.replace(group, opacity=opacity)
            got = r.render(specs).image
            assert torch.equal(got, render(specs, canvas=CANVAS).image)
        assert r.last_recomputed == ["g", "top"]


class TestSpecs:
    def test_pass_through_must_blend_normally(self):
        kid = RenderLayerSpec(id="k", tensors=LayerTensors(torch.rand(3, 2, 2)))
        with pytest.raises(LasagnaError, match="pass-through group .* has blend 'multiply'; expected 'normal'"):
            RenderGroupSpec(id="g", blend="multiply", children=(kid,))

    def test_ids_unique_across_the_tree(self):
        kid = RenderLayerSpec(id="k", tensors=LayerTensors(torch.rand(3, 2, 2)))
        with pytest.raises(LasagnaError, match=r"layers\[1\]\.children\[0\]: id 'k' is used by layers\[0\] too"):
            compile_plan([kid, RenderGroupSpec(id="g", children=(kid,))], (2, 2))

    def test_skip_reasons_of_groups(self):
        kid = RenderLayerSpec(id="k", tensors=LayerTensors(torch.rand(3, 2, 2)))
        cover = RenderLayerSpec(id="cover", tensors=LayerTensors(torch.rand(3, 4, 4)))
        plan = compile_plan(
            [
                RenderGroupSpec(id="hid", children=(dataclasses.replace(kid, id="k1"),), visible=False),
                RenderGroupSpec(id="far", isolated=True, children=(dataclasses.replace(kid, id="k2"),), offset=(9, 9)),
                RenderGroupSpec(id="empty", isolated=True),
                RenderGroupSpec(id="under", isolated=True, children=(dataclasses.replace(kid, id="k3"),)),
                cover,
            ],
            (4, 4),
        )
        assert plan.skipped == {
            "hid": "hidden",
            "k2": "outside-canvas",
            "far": "empty",
            "empty": "empty",
            "under": "occluded",
        }
        assert plan.evaluated == ["cover"]

    def test_a_group_mask_limits_the_group(self):
        kid = RenderLayerSpec(id="k", tensors=LayerTensors(torch.ones(3, 4, 4, dtype=torch.float64)))
        mask = torch.ones(1, 2, 2, dtype=torch.float64)
        group = RenderGroupSpec(id="g", isolated=True, children=(kid,), mask=mask, offset=(1, 1))
        plan = compile_plan([group], (6, 6))
        step = plan.steps[0]
        assert (step.y0, step.y1, step.x0, step.x1) == (1, 3, 1, 3)
        image = render(plan).image
        assert image.sum() == 12 and image[:, 1:3, 1:3].min() == 1
