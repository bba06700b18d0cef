"""Clipping chains (Photoshop's clipping masks) in the compositor, against an independent float64 reference.

The reference composites a flat list with clip flags as psd-tools does (``_apply_clip_layers``): the base's
colour and alpha (without its mask and opacity) seed a canvas, the clipped layers are composited onto it by the
W3C general formula (``group_ref``), and the chain is one source of that colour with the base's alpha × mask ×
opacity, blended with the base's blend. Random chains hold every blend, groups as bases and as clipped layers,
masks, offsets and partial alpha. Also: culling never changes a result, a hidden base hides its chain, the
rectangles of a chain, gradients (gradcheck in float64) and the prefix-cache Renderer after an edit in a chain.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import RenderGroupSpec, RenderLayerSpec, clip_chain
from lasagna.compose.render import render
from lasagna.compose.renderer import Renderer
from tests.compose import group_ref
from tests.compose.numpy_ref import dissolve_u, np64
from tests.compose.test_groups import CANVAS, random_tree


def chains(specs, clips):
    """Bottom-to-top specs with clip flags → the compositor's list (``clip_chain`` per chain)."""
    out: list[list] = []
    for spec, clipped in zip(specs, clips):
        if clipped and out:
            out[-1].append(spec)
        else:
            out.append([spec])
    return [c[0] if len(c) == 1 else clip_chain(c[0], c[1:]) for c in out]


def reference(specs, clips, background=(0.2, 0.4, 0.6), clamp="layer"):
    """(3, H, W) float64: psd-tools' clipping model on ``group_ref``'s formulas (module docstring)."""
    H, W = CANVAS
    ctx = (H, W, False, clamp)
    C = np.empty((3, H, W))
    C[:] = np.asarray(background)[:, None, None]
    A = np.ones((1, H, W))
    runs: list[list] = []
    for spec, clipped in zip(specs, clips):
        if clipped and runs:
            runs[-1].append(spec)
        else:
            runs.append([spec])
    zeros = lambda c: np.zeros((c, H, W))  # noqa: E731
    for base, *clipped in runs:
        if not clipped:
            C, A = group_ref._composite([base], C, A, (0, 0), ctx)
            continue
        if not base.visible:
            continue
        op = float(base.opacity)
        if isinstance(base, RenderGroupSpec):
            bare = dataclasses.replace(base, blend="normal", opacity=1.0, mask=None, isolated=True)
            Cb, Ab = group_ref._composite([bare], zeros(3), zeros(1), (0, 0), ctx)
            m = zeros(1) + op
            if base.mask is not None:
                m = m * group_ref._placed(np64(base.mask), base.offset, H, W, 0.0)
        else:
            t = base.tensors
            color = np64(t.color)
            color = np.broadcast_to(color, (3, *color.shape[1:]))
            alpha = np.ones((1, *color.shape[1:])) if t.alpha is None else np64(t.alpha)
            Cb = group_ref._placed(np.ascontiguousarray(color), base.offset, H, W, 0.0)
            Ab = group_ref._placed(alpha, base.offset, H, W, 0.0)
            mask = np.ones_like(alpha) if t.mask is None else np64(t.mask)
            m = group_ref._placed(mask, base.offset, H, W, 0.0) * op
        Cn, _ = group_ref._composite(clipped, Cb, Ab, (0, 0), ctx)
        a = Ab * m
        if base.blend == "dissolve":
            a = (dissolve_u(H, W) < a).astype(np.float64)
        C, A = group_ref._over(C, A, Cn, a, base.blend)
        if clamp == "layer":
            C = np.clip(C, 0, 1)
    return np.clip(C, 0, 1) if clamp == "output" else C


def random_chains(seed: int):
    specs = random_tree(seed, depth=2, n=6)
    rng = np.random.default_rng(seed)
    clips = [False, False] + [bool(rng.random() < 0.6) for _ in specs[2:]]
    return specs, clips


def box(id, rgb, alpha=None, offset=(0, 0), size=(2, 2), **kw):
    color = torch.tensor(rgb, dtype=torch.float64).view(3, 1, 1).expand(3, *size).clone()
    a = None if alpha is None else torch.full((1, *size), float(alpha), dtype=torch.float64)
    return RenderLayerSpec(id=id, tensors=LayerTensors(color, a), offset=offset, **kw)


class TestReference:
    @pytest.mark.parametrize("seed", range(40))
    def test_random_chains_match_the_float64_reference(self, seed):
        specs, clips = random_chains(seed)
        got = render(chains(specs, clips), canvas=CANVAS, background=(0.2, 0.4, 0.6)).image.numpy()
        np.testing.assert_allclose(got, reference(specs, clips), atol=1e-9, rtol=0)

    @pytest.mark.parametrize("seed", range(12))
    def test_culling_never_changes_a_chain(self, seed):
        specs, clips = random_chains(1000 + seed)
        culled = render(chains(specs, clips), canvas=CANVAS).image
        full = render(chains(specs, clips), canvas=CANVAS, cull=False).image
        torch.testing.assert_close(culled, full, atol=1e-12, rtol=0)

    def test_photoshops_example_half_transparent_base(self):
        """An opaque red layer clipped to a blue base of alpha ½ over black: the chain is red at alpha ½."""
        out = render(chains([box("b", [0, 0, 1.0], 0.5), box("r", [1.0, 0, 0])], [False, True]), canvas=(2, 2))
        assert out.image[:, 0, 0].tolist() == pytest.approx([0.5, 0.0, 0.0], abs=1e-15)

    def test_the_bases_blend_and_opacity_apply_to_the_chain(self):
        base = box("b", [0.5, 0.5, 0.5], blend="multiply", opacity=0.5)
        top = box("t", [0.2, 0.4, 1.0], blend="screen")
        got = render(chains([base, top], [False, True]), canvas=(2, 2), background=(0.8, 0.6, 0.4)).image[:, 0, 0]
        cs, bg = np.array([0.2, 0.4, 1.0]), np.array([0.8, 0.6, 0.4])
        chain = 0.5 + cs - 0.5 * cs  # screen onto the base's grey
        np.testing.assert_allclose(got.numpy(), bg + 0.5 * (bg * chain - bg), atol=1e-12)


class TestPlan:
    def test_a_hidden_base_hides_its_chain(self):
        specs = chains([box("b", [0, 0, 1.0], visible=False), box("r", [1.0, 0, 0])], [False, True])
        out = render(specs, canvas=(2, 2), background=(0.1, 0.2, 0.3))
        assert out.skipped == {"b:clip": "hidden"} and out.evaluated == []
        assert out.image[:, 0, 0].tolist() == pytest.approx([0.1, 0.2, 0.3])

    def test_a_chain_is_the_bases_rectangle_and_clipped_layers_outside_it_are_skipped(self):
        base = box("b", [0, 0, 1.0], offset=(1, 1), size=(2, 2))
        inside = box("in", [1.0, 0, 0], offset=(0, 0), size=(4, 4))
        outside = box("out", [0, 1.0, 0], offset=(5, 5), size=(2, 2))
        out = render(chains([base, inside, outside], [False, True, True]), canvas=(8, 8))
        assert out.skipped == {"out": "outside-base"} and out.evaluated == ["b:clip", "b", "in"]
        expected = torch.zeros(3, 8, 8, dtype=torch.float64)
        expected[0, 1:3, 1:3] = 1.0
        assert torch.equal(out.image, expected)

    def test_an_opaque_clipped_layer_never_occludes_its_base(self):
        base = box("b", [0, 0, 1.0], alpha=0.5)
        out = render(chains([base, box("r", [1.0, 0, 0])], [False, True]), canvas=(2, 2))
        assert "b" in out.evaluated and out.image[0, 0, 0].item() == pytest.approx(0.5)

    def test_a_transparent_base_is_culled_with_its_chain(self):
        base = box("b", [0, 0, 1.0], alpha=0.0)
        out = render(chains([base, box("r", [1.0, 0, 0])], [False, True]), canvas=(2, 2))
        assert out.skipped == {"b": "identity", "b:clip": "identity"}


class TestGradients:
    def test_gradcheck_through_a_chain(self):
        g = torch.Generator().manual_seed(0)
        color = torch.rand(3, 3, 3, generator=g, dtype=torch.float64, requires_grad=True)
        alpha = torch.rand(1, 3, 3, generator=g, dtype=torch.float64) * 0.8 + 0.1
        base_a = torch.rand(1, 3, 3, generator=g, dtype=torch.float64) * 0.8 + 0.1

        def f(c):
            base = RenderLayerSpec(
                id="b", tensors=LayerTensors(torch.full((3, 3, 3), 0.3, dtype=torch.float64), base_a)
            )
            top = RenderLayerSpec(id="t", tensors=LayerTensors(c, alpha), blend="overlay")
            return render(chains([base, top], [False, True]), canvas=(3, 3), clamp="output").image

        assert torch.autograd.gradcheck(f, (color,))


class TestRenderer:
    def test_an_edit_inside_a_chain_is_seen(self):
        specs, clips = random_chains(3)
        renderer = Renderer(CANVAS)
        first = renderer.render(chains(specs, clips)).image
        i = max(i for i, c in enumerate(clips) if c) if any(clips) else len(specs) - 1
        edited = list(specs)
        if isinstance(specs[i], RenderLayerSpec):
            t = specs[i].tensors
            edited[i] = dataclasses.replace(specs[i], tensors=LayerTensors(1.0 - t.color, t.alpha, t.mask))
        else:
            edited[i] = dataclasses.replace(specs[i], opacity=0.5 * float(specs[i].opacity))
        again = renderer.render(chains(edited, clips)).image
        np.testing.assert_allclose(again.numpy(), reference(edited, clips, background=(0, 0, 0)), atol=1e-9)
        assert first.shape == again.shape
