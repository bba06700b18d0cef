"""Renderer: the prefix cache recomputes only from the lowest changed layer and always equals a fresh render."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import RenderLayerSpec
from lasagna.compose.render import render
from lasagna.compose.renderer import Renderer
from lasagna.errors import LasagnaError

CANVAS = (6, 8)


def layers(seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    return [
        RenderLayerSpec(id="base", tensors=LayerTensors(r(3, 6, 8))),
        RenderLayerSpec(id="shade", blend="multiply", range=(0.0, 2.0), tensors=LayerTensors(r(1, 6, 8) * 2)),
        RenderLayerSpec(id="tint", offset=(2, 1), tensors=LayerTensors(r(3, 3, 4), r(1, 3, 4))),
        RenderLayerSpec(id="light", blend="plus", opacity=0.5, tensors=LayerTensors(r(3, 6, 8))),
        RenderLayerSpec(id="top", blend="screen", offset=(-1, -1), tensors=LayerTensors(r(3, 4, 4), r(1, 4, 4))),
    ]


def fresh(ls):
    return render(ls, canvas=CANVAS).image


def test_first_render_equals_render_and_reports_like_it():
    ls = layers()
    r = Renderer(CANVAS)
    got = r.render(ls)
    expect = render(ls, canvas=CANVAS)
    assert torch.equal(got.image, expect.image)
    assert (got.skipped, got.evaluated) == (expect.skipped, expect.evaluated)
    assert r.last_recomputed == ["base", "shade", "tint", "light", "top"]


def test_editing_the_top_layer_recomputes_only_the_top():
    ls = layers()
    r = Renderer(CANVAS)
    r.render(ls)
    for _ in range(3):
        ls[4].tensors.color.mul_(0.5)  # in place
        got = r.render(ls).image
        assert r.last_recomputed == ["top"] and r.last_restart == 4
        assert torch.equal(got, fresh(ls))


def test_editing_a_middle_layer_restarts_there_from_the_second_edit_on():
    ls = layers()
    r = Renderer(CANVAS)
    r.render(ls)
    ls[2].tensors.alpha.mul_(0.5)
    r.render(ls)  # the first edit of "tint" restarts below it and takes a snapshot before it
    ls[2].tensors.alpha.mul_(0.5)
    got = r.render(ls).image
    assert r.last_recomputed == ["tint", "light", "top"] and r.last_restart == 2
    assert torch.equal(got, fresh(ls))
    ls[4].tensors.color.mul_(0.5)  # the top snapshot survived
    assert torch.equal(r.render(ls).image, fresh(ls)) and r.last_recomputed == ["top"]


def test_unchanged_stack_returns_the_same_image_unless_it_was_modified():
    ls = layers()
    r = Renderer(CANVAS)
    first = r.render(ls).image
    again = r.render(ls).image
    assert again is first and r.last_recomputed == []
    expect = first.clone()
    first.zero_()  # the caller wrote into it: it is recomputed, not returned again
    third = r.render(ls).image
    assert third is not first and torch.equal(third, expect) and r.last_recomputed == ["top"]


@pytest.mark.parametrize(
    "edit", ["replace tensor", "opacity", "visible", "offset", "blend", "range", "remove", "append"]
)
def test_every_kind_of_edit_is_detected(edit):
    ls = layers()
    r = Renderer(CANVAS)
    r.render(ls)
    r.render(ls)
    mid = ls[2]
    if edit == "replace tensor":
        ls[2] = dataclasses.replace(mid, tensors=LayerTensors(torch.rand(3, 3, 4), mid.tensors.alpha))
    elif edit == "opacity":
        ls[2] = dataclasses.replace(mid, opacity=0.5)
    elif edit == "visible":
        ls[2] = dataclasses.replace(mid, visible=False)
    elif edit == "offset":
        ls[2] = dataclasses.replace(mid, offset=(3, 1))
    elif edit == "blend":
        ls[2] = dataclasses.replace(mid, blend="screen")
    elif edit == "range":
        ls[1] = dataclasses.replace(ls[1], range=(0.0, 3.0), tensors=LayerTensors(ls[1].tensors.color * 1.5))
    elif edit == "remove":
        del ls[2]
    else:
        ls.append(RenderLayerSpec(id="extra", tensors=LayerTensors(torch.rand(3, 2, 2))))
    got = r.render(ls).image
    assert torch.equal(got, fresh(ls))
    assert r.last_recomputed  # something was recomputed


def test_replaced_tensor_with_recycled_id_is_detected():
    ls = layers()
    r = Renderer(CANVAS)
    r.render(ls)
    for value in (0.2, 0.7, 0.2, 0.9):
        ls[4] = dataclasses.replace(ls[4], tensors=LayerTensors(torch.full((3, 4, 4), value), ls[4].tensors.alpha))
        assert torch.equal(r.render(ls).image, fresh(ls))


def test_zero_budget_still_correct():
    ls = layers()
    r = Renderer(CANVAS, cache_bytes=0)
    r.render(ls)
    ls[4].tensors.color.mul_(0.5)
    assert torch.equal(r.render(ls).image, fresh(ls))
    assert r.cached_bytes == 0 and r.last_restart == 0


def test_budget_is_respected():
    canvas_bytes = 3 * 6 * 8 * 4
    r = Renderer(CANVAS, cache_bytes=2 * canvas_bytes)
    ls = layers()
    r.render(ls)
    for i in (1, 2, 3, 4, 1, 2):
        ls[i].tensors.color.mul_(0.9)
        assert torch.equal(r.render(ls).image, fresh(ls))
        assert r.cached_bytes <= 2 * canvas_bytes


def test_learned_top_layer_training_loop():
    ls = layers()
    theta = torch.zeros(3, 4, 4, requires_grad=True)
    r = Renderer(CANVAS, clamp="output")
    for step in range(3):
        ls[4] = dataclasses.replace(ls[4], tensors=LayerTensors(torch.sigmoid(theta), ls[4].tensors.alpha))
        image = r.render(ls).image
        expect = render(ls, canvas=CANVAS, clamp="output").image
        assert torch.allclose(image, expect, atol=1e-7)
        (g1,) = torch.autograd.grad(image.square().sum(), theta, retain_graph=True)
        (g2,) = torch.autograd.grad(expect.square().sum(), theta)
        assert torch.allclose(g1, g2, atol=1e-6) and g1.abs().sum() > 0
        if step:
            assert r.last_recomputed == ["top"]
        with torch.no_grad():
            theta.add_(0.1)


def test_snapshot_taken_without_grad_does_not_cut_the_graph():
    ls = layers()
    r = Renderer(CANVAS)
    with torch.no_grad():
        r.render(ls)  # snapshots everywhere, no autograd
    learned = ls[1].tensors.color.clone().requires_grad_()
    ls[1] = dataclasses.replace(ls[1], tensors=LayerTensors(learned))
    ls[4].tensors.color.mul_(0.5)
    r.render(ls).image.sum().backward()
    assert learned.grad is not None and learned.grad.abs().sum() > 0


def test_config_errors():
    with pytest.raises(LasagnaError, match="cache_bytes is -1"):
        Renderer(CANVAS, cache_bytes=-1)
    with pytest.raises(LasagnaError, match="canvas is"):
        Renderer((0, 1))


def test_out_parameter():
    ls = layers()
    r = Renderer(CANVAS)
    out = torch.empty(3, *CANVAS)
    assert r.render(ls, out=out).image is out and torch.equal(out, fresh(ls))
    ls[4].tensors.color.mul_(0.5)
    assert r.render(ls, out=out).image is out and torch.equal(out, fresh(ls)) and r.last_recomputed == ["top"]
    assert r.render(ls, out=out).image is out and r.last_recomputed == []  # unchanged, and out holds it
    with pytest.raises(LasagnaError, match="out is \\(3, 5, 8\\)"):
        r.render(ls, out=torch.empty(3, 5, 8))
    learned = [dataclasses.replace(ls[0], tensors=LayerTensors(ls[0].tensors.color.clone().requires_grad_()))] + ls[1:]
    with pytest.raises(LasagnaError, match="needs gradients"):
        r.render(learned, out=out)
