"""The render plan: rectangles, skip reasons, occlusion, clamp decisions, errors, the document adapter."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import RenderLayerSpec, compile_plan, plan_from_document
from lasagna.compose.render import render
from lasagna.errors import LasagnaError


def spec(id, h=4, w=4, c=3, value=None, alpha=None, **kw):
    color = torch.rand(c, h, w) if value is None else torch.full((c, h, w), float(value))
    return RenderLayerSpec(id=id, tensors=LayerTensors(color, alpha), **kw)


def test_rectangles_are_clipped_to_the_canvas():
    plan = compile_plan([spec("a", h=5, w=6, offset=(-2, 3))], (6, 8))
    (s,) = plan.steps
    assert (s.y0, s.y1, s.x0, s.x1, s.ly0, s.lx0) == (3, 6, 0, 4, 0, 2)
    assert s.layer_slice()[1:] == (slice(0, 3), slice(2, 6))
    assert not s.full


@pytest.mark.parametrize(
    "layer, reason",
    [
        (dict(visible=False), "hidden"),
        (dict(opacity=0.0), "zero-opacity"),
        (dict(opacity=torch.tensor(0.0)), "zero-opacity"),
        (dict(offset=(8, 0)), "outside-canvas"),
        (dict(offset=(-4, 0)), "outside-canvas"),
        (dict(offset=(0, 6)), "outside-canvas"),
        (dict(blend="multiply", value=1.0), "identity"),
        (dict(blend="plus", value=0.0), "identity"),
        (dict(blend="screen", value=0.0), "identity"),
        (dict(alpha=torch.zeros(1, 4, 4)), "identity"),
    ],
)
def test_skip_reasons_are_reported(layer, reason):
    result = render([spec("base", 6, 8), spec("x", **layer)], canvas=(6, 8))
    assert result.skipped == {"x": reason}
    assert result.evaluated == ["base"]


def test_occluded_by_an_opaque_normal_layer_above():
    layers = [
        spec("base", 6, 8),
        spec("small", 2, 2, offset=(1, 1)),
        spec("cover", 3, 3, offset=(0, 0)),
        spec("partly", 2, 2, offset=(2, 2)),
        spec("top", 2, 2, offset=(2, 2), alpha=torch.full((1, 2, 2), 0.5)),
    ]
    plan = compile_plan(layers, (6, 8))
    assert plan.skipped == {"small": "occluded"}
    # "partly" sticks out of "cover" (rows/cols 2..3 vs 0..2): live. A translucent layer occludes nothing.
    assert plan.evaluated == ["base", "cover", "partly", "top"]


def test_opaque_full_canvas_layer_hides_background_and_everything_below():
    layers = [
        spec("a", 6, 8),
        spec("b", 2, 2, blend="plus"),
        spec("cover", 6, 8, alpha=torch.ones(1, 6, 8)),
        spec("c", 2, 2, blend="multiply"),
    ]
    result = render(layers, canvas=(6, 8), background=(1.0, 0.0, 0.0))
    assert result.skipped == {"a": "occluded", "b": "occluded"}
    assert result.evaluated == ["cover", "c"]
    # Neither the background nor the layers below can show: any background gives the same image.
    other = render(layers[2:], canvas=(6, 8), background=(0.0, 1.0, 0.5), cull=False).image
    assert torch.equal(result.image, other)
    cover_only = render([spec("cover", 6, 8, value=0.25)], canvas=(6, 8), background=(1.0, 0.0, 0.0)).image
    assert torch.equal(cover_only, torch.full((3, 6, 8), 0.25))


def test_occluder_must_have_opacity_one_and_no_mask_below_one():
    mask = torch.ones(1, 4, 4)
    mask[0, 0, 0] = 0.5
    masked = RenderLayerSpec(id="top", tensors=LayerTensors(torch.rand(3, 4, 4), None, mask))
    for top in (spec("top", opacity=0.99), masked):
        assert compile_plan([spec("below"), top], (4, 4)).skipped == {}


def test_gradient_carrying_opacity_is_never_culled_by_value():
    op = torch.tensor(0.0, requires_grad=True)
    plan = compile_plan([spec("base"), spec("learned", opacity=op)], (4, 4))
    assert plan.skipped == {} and plan.evaluated == ["base", "learned"]
    # ... nor does it occlude (its gradient needs the layers below), nor does a learned identity layer cull.
    op1 = torch.tensor(1.0, requires_grad=True)
    ones = torch.ones(1, 4, 4, requires_grad=True)
    plan = compile_plan(
        [
            spec("base"),
            spec("top", opacity=op1),
            RenderLayerSpec(id="mult", blend="multiply", tensors=LayerTensors(ones)),
        ],
        (4, 4),
    )
    assert plan.skipped == {}


def test_cull_false_keeps_the_no_op_layers():
    layers = [
        spec("base"),
        spec("zero", opacity=0.0),
        spec("id", blend="multiply", value=1.0),
        spec("hidden", visible=False),
    ]
    plan = compile_plan(layers, (4, 4), cull=False)
    assert plan.skipped == {"hidden": "hidden"}
    assert plan.evaluated == ["base", "zero", "id"]


def test_clamp_decisions():
    layers = [
        spec("base", value=0.5),
        spec("n", alpha=torch.rand(1, 4, 4)),
        RenderLayerSpec(id="m2", blend="multiply", range=(0.0, 2.0), tensors=LayerTensors(torch.rand(1, 4, 4) * 2)),
        spec("m1", blend="multiply", c=1),
        spec("p", blend="plus"),
        RenderLayerSpec(
            id="learned",
            blend="multiply",
            range=(0.0, 1.0),
            tensors=LayerTensors(torch.rand(1, 4, 4, requires_grad=True)),
        ),
    ]
    steps = {s.spec.id: (s.clamp_lo, s.clamp_hi) for s in compile_plan(layers, (4, 4)).steps}
    assert steps["base"] == steps["n"] == steps["m1"] == (False, False)
    assert steps["m2"][1] and steps["p"][1]
    assert steps["learned"] == (False, False)  # its declared range proves it
    out = {s.spec.id: (s.clamp_lo, s.clamp_hi) for s in compile_plan(layers, (4, 4), clamp="output").steps}
    assert set(out.values()) == {(False, False)}


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(blend="grain-merge"), "unknown blend 'grain-merge'; expected one of normal, multiply, screen, plus, "),
        (dict(opacity=1.5), "opacity is 1.5; expected a number in \\[0, 1\\]"),
        (dict(opacity=torch.tensor(2.0)), "opacity spans \\[2.0, 2.0\\]"),
        (dict(opacity=torch.ones(2)), "opacity tensor has shape \\(2,\\)"),
        (dict(offset=(0.5, 0)), "offset is \\(0.5, 0\\); expected two integers"),
        (dict(range=(1.0, 0.0)), "range is \\(1.0, 0.0\\); expected \\(lo, hi\\)"),
        (dict(visible=1), "visible is 1; expected true or false"),
    ],
)
def test_spec_exceptions(kwargs, match):
    with pytest.raises(LasagnaError, match=match) as info:
        spec("x", **kwargs)
    assert str(info.value).startswith("layer 'x'")


@pytest.mark.parametrize(
    "args, match",
    [
        (dict(canvas=(0, 4)), "canvas is \\(0, 4\\)"),
        (dict(canvas=(4, 4), background=(0, 0)), "background is \\(0, 0\\)"),
        (dict(canvas=(4, 4), blend_space="lab"), "blend_space is 'lab'"),
        (dict(canvas=(4, 4), clamp="always"), "clamp is 'always'"),
    ],
)
def test_compile_exceptions(args, match):
    with pytest.raises(LasagnaError, match=match):
        compile_plan([spec("a")], **args)


def test_duplicate_ids_and_unbroadcastable_batches():
    with pytest.raises(LasagnaError, match="layers\\[1\\]: id 'a' is used by layers\\[0\\] too"):
        compile_plan([spec("a"), spec("a")], (4, 4))
    batched = [
        RenderLayerSpec(id="a", tensors=LayerTensors(torch.rand(2, 3, 4, 4))),
        RenderLayerSpec(id="b", tensors=LayerTensors(torch.rand(3, 3, 4, 4), torch.rand(3, 1, 4, 4) * 0.5)),
    ]
    with pytest.raises(LasagnaError, match="layer 'b': batch dimensions \\(3,\\) do not broadcast with \\(2,\\)"):
        compile_plan(batched, (4, 4))


def test_render_needs_a_canvas_for_a_list_of_layers():
    with pytest.raises(LasagnaError, match="canvas is missing"):
        render([spec("a")])


# ---- the document adapter ----------------------------------------------------------------------


def fake_document(**overrides):
    layers = [
        SimpleNamespace(
            id="base",
            kind="pixels",
            blend="normal",
            opacity=1.0,
            visible=True,
            offset=SimpleNamespace(x=0, y=0),
            range=(0.0, 1.0),
            mask=None,
        ),
        SimpleNamespace(
            id="shade",
            kind="pixels",
            blend="multiply",
            opacity=0.5,
            visible=True,
            offset=SimpleNamespace(x=1, y=0),
            range=(0.0, 2.0),
            mask="masks/shade.png",
        ),
        SimpleNamespace(
            id="tint",
            kind="solid",
            blend="normal",
            opacity=1.0,
            visible=True,
            color=(1.0, 0.5, 0.0, 0.25),
            size=SimpleNamespace(width=2, height=2),
            offset=SimpleNamespace(x=2, y=2),
            range=(0.0, 1.0),
            mask=None,
        ),
        SimpleNamespace(
            id="relit",
            kind="learned",
            source=None,
            blend="multiply",
            opacity=1.0,
            visible=True,
            offset=SimpleNamespace(x=0, y=0),
            range=(0.0, 2.0),
            mask=None,
        ),
    ]
    doc = SimpleNamespace(
        canvas=SimpleNamespace(width=5, height=4, background=(0.1, 0.2, 0.3)),
        blend_space="srgb",
        clamp="layer",
        layers=layers,
    )
    for k, v in overrides.items():
        setattr(doc, k, v)
    return doc


def test_plan_from_document_matches_hand_built_specs():
    base = LayerTensors(torch.rand(3, 4, 5))
    shade = LayerTensors(torch.rand(1, 4, 4) * 2, None, torch.rand(1, 4, 4))
    plan = plan_from_document(fake_document(), {"base": base, "shade": shade})
    assert plan.evaluated == ["base", "shade", "tint"]  # "relit" has no pixels yet
    assert (plan.canvas, plan.background, plan.blend_space, plan.clamp) == ((4, 5), (0.1, 0.2, 0.3), "srgb", "layer")
    tint = LayerTensors(torch.tensor([1.0, 0.5, 0.0]).view(3, 1, 1).expand(3, 2, 2), torch.full((1, 2, 2), 0.25))
    by_hand = [
        RenderLayerSpec(id="base", tensors=base),
        RenderLayerSpec(id="shade", tensors=shade, blend="multiply", opacity=0.5, offset=(1, 0), range=(0.0, 2.0)),
        RenderLayerSpec(id="tint", tensors=tint, offset=(2, 2)),
    ]
    expect = render(by_hand, canvas=(4, 5), background=(0.1, 0.2, 0.3)).image
    assert torch.equal(render(plan).image, expect)


def test_plan_from_document_errors():
    with pytest.raises(LasagnaError, match="layers\\[0\\]: no tensors for pixels layer 'base'"):
        plan_from_document(fake_document(), {})
    with pytest.raises(LasagnaError, match="layers\\[1\\].mask: names mask 'masks/shade.png'"):
        plan_from_document(
            fake_document(), {"base": LayerTensors(torch.rand(3, 4, 5)), "shade": LayerTensors(torch.rand(1, 4, 4))}
        )


def test_plan_from_real_document_models():
    models = pytest.importorskip("lasagna.document.models")
    doc = models.Document.model_validate(
        {
            "format": "lasagna.stack",
            "version": 1,
            "canvas": {"width": 4, "height": 3, "background": [0.0, 0.5, 1.0]},
            "blend_space": "linear",
            "layers": [
                {"id": "base", "kind": "pixels", "source": "layers/base.png"},
                {
                    "id": "light",
                    "kind": "pixels",
                    "source": "layers/light.png",
                    "blend": "additive",
                    "range": [-1.0, 1.0],
                    "offset": {"x": 1, "y": -1},
                    "opacity": 0.5,
                },
            ],
        }
    )
    tensors = {"base": LayerTensors(torch.rand(3, 3, 4)), "light": LayerTensors(torch.rand(3, 2, 2) * 2 - 1)}
    plan = plan_from_document(doc, tensors)
    assert plan.evaluated == ["base", "light"] and plan.blend_space == "linear"
    light = plan.steps[1]
    assert light.spec.blend == "plus" and light.spec.range == (-1.0, 1.0) and (light.y0, light.x0) == (0, 1)
