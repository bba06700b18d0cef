"""Adjustment layers: each adjustment against its float64 numpy reference (``tests/adjust_ref.py``: the formulas per
pixel, no tables), gradients in float64 (``gradcheck``) in the colour and the parameters, refusals, and adjustment
layers composited in stacks (opaque canvas, isolated groups, clipping chains, the banded and recorded engines, the
prefix-cache Renderer) against ``tests/support/reference.py``'s float64 composite of the same stack folder.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.compose.adjust import ADJUSTMENTS, Adjustment
from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import RenderLayerSpec, adjustment_tensors, compile_plan
from lasagna.compose.render import render
from lasagna.compose.renderer import Renderer
from lasagna.document import Document
from lasagna.errors import DocumentError, LasagnaError
from lasagna.io.render import render_stack
from lasagna.io.stack import Stack, save_stack
from tests.adjust_ref import adjust_reference
from tests.support.reference import composite_reference

# One of each, with parameters away from the identity (document units; see lasagna/document/adjustment.py).
CASES = {
    "levels": {
        "type": "levels",
        "rgb": {"in_black": 0.1, "in_white": 0.85, "gamma": 1.4, "out_black": 0.05, "out_white": 0.95},
        "red": {"in_black": 0.0, "in_white": 0.7, "gamma": 0.8, "out_black": 0.1, "out_white": 1.0},
    },
    "curves": {
        "type": "curves",
        "rgb": [[0.0, 0.1], [0.3, 0.5], [0.8, 0.7], [1.0, 1.0]],
        "blue": [[0.1, 0.0], [0.9, 1.0]],
    },
    "hue-saturation": {"type": "hue-saturation", "hue": 40.0, "saturation": -30.0, "lightness": 12.0},
    "hue-saturation+": {"type": "hue-saturation", "hue": -70.0, "saturation": 45.0, "lightness": -20.0},
    "hue-ranges": {
        "type": "hue-saturation",
        "hue": 10.0,
        "saturation": 15.0,
        "ranges": [
            {"range": [315.0, 345.0, 15.0, 45.0], "hue": 25.0, "saturation": 40.0, "lightness": -30.0},
            {"range": [75.0, 105.0, 135.0, 165.0], "hue": -40.0, "saturation": -60.0, "lightness": 20.0},
            {"range": [195.0, 225.0, 255.0, 285.0], "lightness": 0.0},
        ],
    },
    "colorize": {"type": "hue-saturation", "colorize": {"hue": 210.0, "saturation": 60.0, "lightness": -15.0}},
    "brightness-contrast": {"type": "brightness-contrast", "brightness": 40.0, "contrast": 30.0},
    "brightness-contrast-": {"type": "brightness-contrast", "brightness": -90.0, "contrast": -40.0},
    "legacy": {"type": "brightness-contrast", "brightness": 25.0, "contrast": 35.0, "legacy": True},
    "exposure": {"type": "exposure", "exposure": 0.8, "offset": 0.02, "gamma": 1.2},
    "invert": {"type": "invert"},
    "posterize": {"type": "posterize", "levels": 5},
    "threshold": {"type": "threshold", "level": 0.45},
    "channel-mixer": {
        "type": "channel-mixer",
        "red": [80.0, 30.0, -20.0, 5.0],
        "green": [-10.0, 120.0, 0.0, -8.0],
        "blue": [25.0, 25.0, 60.0, 0.0],
    },
    "mixer-gray": {"type": "channel-mixer", "gray": [40.0, 40.0, 20.0, 3.0]},
    "color-balance": {
        "type": "color-balance",
        "shadows": [30.0, -20.0, 10.0],
        "midtones": [-40.0, 15.0, 55.0],
        "highlights": [10.0, 35.0, -25.0],
    },
    "color-balance-free": {"type": "color-balance", "midtones": [60.0, -30.0, 0.0], "preserve_luminosity": False},
    "vibrance": {"type": "vibrance", "vibrance": 60.0, "saturation": -15.0},
    "vibrance-": {"type": "vibrance", "vibrance": -45.0, "saturation": 25.0},
    "black-and-white": {"type": "black-and-white", "reds": 120.0, "yellows": -30.0, "blues": 200.0},
    "tinted": {"type": "black-and-white", "tint": [0.8, 0.6, 0.3]},
    "gradient-map": {
        "type": "gradient-map",
        "stops": [
            {"location": 0.05, "color": [0.1, 0.0, 0.3]},
            {"location": 0.5, "color": [0.9, 0.2, 0.1], "midpoint": 0.3},
            {"location": 0.9, "color": [1.0, 0.95, 0.6], "midpoint": 0.7},
        ],
    },
    "gradient-map-reversed": {
        "type": "gradient-map",
        "stops": [{"location": 0.0, "color": [0.0, 0.0, 0.0]}, {"location": 1.0, "color": [1.0, 0.5, 0.2]}],
        "reverse": True,
    },
    "photo-filter": {"type": "photo-filter", "color": [0.0, 0.43, 1.0], "density": 60.0},
    "photo-filter-free": {"type": "photo-filter", "density": 35.0, "preserve_luminosity": False},
}
# Tables are read by linear interpolation (LUT_SIZE entries): within this of the per-pixel formulas, except where
# a gamma's t^(1/γ) bends fastest (first table interval), which the inputs below keep clear of.
TABLE_TOL = 2e-5


def params(case: dict) -> dict:
    from pydantic import TypeAdapter

    from lasagna.document.adjustment import Adjustment as Model  # the document's defaults filled in

    return TypeAdapter(Model).validate_python(case).model_dump(exclude={"type"})


def colours(seed: int = 0, h: int = 9, w: int = 11) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(3, h, w, generator=g, dtype=torch.float64) * 0.96 + 0.02


class TestAdjustments:
    @pytest.mark.parametrize("name", CASES)
    def test_reference_values(self, name):
        case = CASES[name]
        C = colours()
        got = Adjustment(case["type"], params(case))(C).numpy()
        want = adjust_reference({**params(case), "type": case["type"]}, C.numpy())
        if case["type"] in ("posterize", "threshold"):  # steps: compare away from the edges
            assert np.mean(np.abs(got - want) > 1e-9) < 0.01
        else:
            tabled = case["type"] in ("levels", "curves", "brightness-contrast", "exposure", "gradient-map")
            np.testing.assert_allclose(got, want, atol=TABLE_TOL if tabled else 1e-9)

    @pytest.mark.parametrize("name", CASES)
    def test_shapes_and_range(self, name):
        case = CASES[name]
        C = torch.rand(2, 3, 4, 5)
        out = Adjustment(case["type"], params(case))(C)
        assert out.shape == C.shape and out.dtype == C.dtype
        assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0

    def test_every_adjustment_has_a_case(self):
        assert {c["type"] for c in CASES.values()} == set(ADJUSTMENTS)

    @pytest.mark.parametrize(
        "kind, make",
        [
            (
                "levels",
                lambda g: {"rgb": {"in_black": 0.05, "in_white": 0.9, "gamma": g, "out_black": 0.0, "out_white": 1.0}},
            ),
            ("exposure", lambda g: {"exposure": g - 0.5, "offset": 0.01, "gamma": 1.1}),
            ("brightness-contrast", lambda g: {"brightness": 30.0 * g, "contrast": 20.0 * g, "legacy": False}),
            (
                "hue-saturation",
                lambda g: {"hue": 30.0 * g, "saturation": -20.0 * g, "lightness": -10.0 * g, "colorize": None},
            ),
        ],
    )
    def test_gradcheck_in_parameters_and_colour(self, kind, make):
        g = torch.tensor(1.3, dtype=torch.float64, requires_grad=True)
        C = colours(1, 3, 4).requires_grad_(True)
        torch.autograd.gradcheck(lambda g, C: Adjustment(kind, make(g))(C), (g, C), atol=1e-5)

    @pytest.mark.parametrize(
        "kind, make",
        [
            (
                "channel-mixer",
                lambda g: {
                    "red": [80 * g, 20.0, -10.0, 5 * g],
                    "green": [0.0, 100.0, 0.0, 0.0],
                    "blue": [10.0, -20 * g, 90.0, 0.0],
                },
            ),
            (
                "color-balance",
                lambda g: {
                    "shadows": [20 * g, 0.0, -10.0],
                    "midtones": [-30 * g, 10.0, 20 * g],
                    "highlights": [5.0, 5 * g, 0.0],
                    "preserve_luminosity": True,
                },
            ),
            ("vibrance", lambda g: {"vibrance": 40 * g, "saturation": -20 * g}),
            (
                "black-and-white",
                lambda g: {
                    "reds": 40 * g,
                    "yellows": 60.0,
                    "greens": 40 * g,
                    "cyans": 60.0,
                    "blues": 20 * g,
                    "magentas": 80.0,
                    "tint": [0.7, 0.5 * g, 0.3],
                },
            ),
            (
                "gradient-map",
                lambda g: {
                    "stops": [
                        {"location": 0.0, "color": [0.1 * g, 0.0, 0.3]},
                        {"location": 0.4 * g, "color": [0.9, 0.2, 0.1], "midpoint": 0.4},
                        {"location": 1.0, "color": [1.0, 0.9 * g, 0.6]},
                    ],
                    "reverse": False,
                },
            ),
            ("photo-filter", lambda g: {"color": [0.9, 0.5 * g, 0.1], "density": 40 * g, "preserve_luminosity": True}),
        ],
    )
    def test_gradcheck_new_adjustments(self, kind, make):  # hue ranges: see test_gradcheck_hue_ranges
        g = torch.tensor(0.9, dtype=torch.float64, requires_grad=True)
        C = colours(3, 3, 4).requires_grad_(True)
        torch.autograd.gradcheck(lambda g, C: Adjustment(kind, make(g))(C), (g, C), atol=1e-5)

    def test_gradcheck_hue_ranges(self):
        def f(g, C):
            ranges = [
                {"range": [300.0, 340.0, 20.0, 60.0], "hue": 20 * g, "saturation": 30 * g, "lightness": -25 * g},
                {"range": [90.0, 120.0, 180.0, 230.0], "hue": -10.0, "saturation": -40 * g, "lightness": 15 * g},
            ]
            return Adjustment(
                "hue-saturation", {"hue": 0.0, "saturation": 0.0, "lightness": 0.0, "colorize": None, "ranges": ranges}
            )(C)

        g = torch.tensor(0.8, dtype=torch.float64, requires_grad=True)
        C = colours(4, 3, 4).requires_grad_(True)
        torch.autograd.gradcheck(f, (g, C), atol=1e-5)

    def test_gradcheck_curve_points(self):
        pts = torch.tensor(
            [[0.0, 0.05], [0.35, 0.55], [0.7, 0.8], [1.0, 0.95]], dtype=torch.float64, requires_grad=True
        )
        C = colours(2, 3, 4)
        torch.autograd.gradcheck(lambda p: Adjustment("curves", {"rgb": p})(C), (pts,), atol=1e-5)

    def test_refusals_are_one_line(self):
        with pytest.raises(LasagnaError, match="unknown adjustment 'sharpen'"):
            Adjustment("sharpen", {})
        with pytest.raises(LasagnaError, match="finite"):
            Adjustment("exposure", {"exposure": float("nan"), "offset": 0.0, "gamma": 1.0})


def doc(adjustment: dict, **layer) -> dict:
    return {
        "format": "lasagna.stack",
        "version": 1,
        "canvas": {"width": 4, "height": 4},
        "layers": [
            {"id": "a", "kind": "solid", "color": [0.2, 0.5, 0.7]},
            {"id": "adj", "kind": "adjustment", "adjustment": adjustment, **layer},
        ],
    }


@pytest.mark.parametrize(
    "adjustment, message",
    [
        ({"type": "curves", "rgb": [[0.0, 0.0]] * 10**6}, "expected at most 64"),
        ({"type": "curves", "rgb": [[0.5, 0.0], [0.2, 1.0]]}, "strictly increasing"),
        ({"type": "levels", "rgb": {"gamma": float("nan")}}, "finite"),
        ({"type": "levels", "rgb": {"in_black": 0.6, "in_white": 0.4}}, "in_black < in_white"),
        ({"type": "sharpen"}, "expected one of 'levels'"),
        ({"type": "brightness-contrast", "brightness": 120.0, "legacy": True}, "within ±100"),
        ({"type": "posterize", "levels": 1}, "greater than or equal to 2|expected"),
        ({"type": "channel-mixer", "red": [300.0, 0.0, 0.0, 0.0]}, "less than or equal to 200"),
        ({"type": "color-balance", "shadows": [0.0, float("nan"), 0.0]}, "finite"),
        ({"type": "vibrance", "vibrance": 150.0}, "less than or equal to 100"),
        ({"type": "black-and-white", "tint": [0.5, 0.5]}, "tint\\[2\\]: required field is missing"),
        (
            {
                "type": "gradient-map",
                "stops": [{"location": 0.8, "color": [0, 0, 0]}, {"location": 0.2, "color": [1, 1, 1]}],
            },
            "not sorted|valid number",
        ),
        ({"type": "gradient-map", "stops": [{"location": 0.0, "color": [0.0, 0.0, 0.0]}] * 100}, "at most 64"),
        ({"type": "photo-filter", "density": -1.0}, "greater than or equal to 0"),
        (
            {"type": "hue-saturation", "ranges": [{"range": [0.0, 10.0, 20.0, 30.0], "hue": 200.0}]},
            "less than or equal to 180",
        ),
    ],
)
def test_bad_parameters_are_one_line(adjustment, message):
    with pytest.raises(DocumentError, match=message) as err:
        Document.from_dict(doc(adjustment))
    assert "\n" not in str(err.value) and "layers[1].adjustment" in str(err.value)


def random_stack(tmp_path, seed: int, blend_space="srgb", clamp="layer"):
    """A stack folder: a random base, a group holding a partly transparent layer and an adjustment, a clipped
    adjustment on a masked layer, and an adjustment of every kind above, some masked, of various blends."""
    rng = np.random.default_rng(seed)
    H, W = 12, 14

    def pix():
        return LayerTensors(
            torch.from_numpy(rng.random((3, H, W))).float(), torch.from_numpy(rng.random((1, H, W))).float()
        )

    layers = [{"id": "base", "kind": "pixels", "source": "layers/base.png"}]
    tensors = {"base": LayerTensors(torch.from_numpy(rng.random((3, H, W))).float())}
    layers.append(
        {
            "id": "g",
            "kind": "group",
            "isolated": True,
            "layers": [
                {"id": "inner", "kind": "pixels", "source": "layers/inner.png"},
                {"id": "g-adj", "kind": "adjustment", "adjustment": CASES["curves"]},
            ],
        }
    )
    tensors["inner"] = pix()
    layers += [
        {"id": "under", "kind": "pixels", "source": "layers/under.png", "opacity": 0.8},
    ]
    tensors["under"] = pix()
    blends = ["normal", "multiply", "screen", "overlay", "color", "difference"]
    for i, (name, case) in enumerate(CASES.items()):
        lid = f"adj{i}"
        entry = {"id": lid, "kind": "adjustment", "adjustment": case, "opacity": float(rng.uniform(0.4, 1.0))}
        entry["blend"] = blends[i % len(blends)]
        if i % 3 == 0:
            entry["mask"] = f"masks/{lid}.png"
            entry["offset"] = {"x": int(rng.integers(-3, 4)), "y": int(rng.integers(-3, 4))}
            mask = torch.from_numpy(rng.random((1, H - 2, W - 4))).float()
            from lasagna.io.stack import group_mask_tensors

            tensors[lid] = group_mask_tensors(mask)
        layers.append(entry)
    d = Document.from_dict(
        {
            "format": "lasagna.stack",
            "version": 1,
            "canvas": {"width": W, "height": H, "background": [0.3, 0.3, 0.3]},
            "blend_space": blend_space,
            "clamp": clamp,
            "layers": layers,
        }
    )
    folder = tmp_path / f"s{seed}"
    save_stack(Stack(d, None, tensors, {k: 16 for k in tensors}), folder)
    from lasagna.io.stack import load_stack

    return load_stack(folder), folder


@pytest.mark.parametrize("seed, blend_space", [(0, "srgb"), (1, "srgb"), (2, "linear")])
def test_stacks_composite_as_the_float64_reference(tmp_path, seed, blend_space):
    stack, folder = random_stack(tmp_path, seed, blend_space)
    got = render_stack(stack, dtype=torch.float64).image.numpy()
    want = composite_reference(folder)
    err = np.abs(got - want)
    # Posterize and threshold are steps: a value within rounding of an edge may land on either side.
    assert np.mean(err > 1e-4) < 0.02 and np.median(err) < 1e-6
    fast = render_stack(stack).image.numpy()  # float32, the banded engine
    assert np.mean(np.abs(fast - got) > 1e-4) < 0.02


def test_banded_and_recorded_engines_agree_and_gradients_reach_parameters():
    torch.manual_seed(0)
    H, W = 6, 7
    base = RenderLayerSpec(id="base", tensors=LayerTensors(torch.rand(3, H, W, dtype=torch.float64)))
    g = torch.tensor(1.2, dtype=torch.float64, requires_grad=True)
    adj = Adjustment(
        "levels", {"rgb": {"in_black": 0.1, "in_white": 0.9, "gamma": g, "out_black": 0.0, "out_white": 1.0}}
    )
    mask = torch.rand(1, H, W, dtype=torch.float64)
    spec = RenderLayerSpec(id="adj", tensors=adjustment_tensors(mask, W, H), adjust=adj, opacity=0.8, blend="overlay")
    plan = compile_plan([base, spec], (H, W))
    img = render(plan).image
    img.sum().backward()
    assert g.grad is not None and torch.isfinite(g.grad)
    with torch.no_grad():
        fast = render(plan).image
    torch.testing.assert_close(fast, img.detach())


def test_renderer_re_renders_after_a_parameter_edit():
    torch.manual_seed(1)
    H, W = 5, 6
    base = RenderLayerSpec(id="base", tensors=LayerTensors(torch.rand(3, H, W)))
    r = Renderer((H, W))

    def spec(level):
        return RenderLayerSpec(
            id="t", tensors=adjustment_tensors(None, W, H), adjust=Adjustment("threshold", {"level": level})
        )

    a = r.render([base, spec(0.2)]).image.clone()
    b = r.render([base, spec(0.8)]).image
    fresh = render([base, spec(0.8)], canvas=(H, W)).image
    assert not torch.equal(a, b) and torch.equal(b, fresh)


def test_a_zero_mask_is_culled_and_the_layer_is_never_an_occluder():
    H, W = 4, 4
    base = RenderLayerSpec(id="base", tensors=LayerTensors(torch.rand(3, H, W)))
    zero = RenderLayerSpec(id="z", tensors=adjustment_tensors(torch.zeros(1, H, W), W, H), adjust=Adjustment("invert"))
    full = RenderLayerSpec(id="f", tensors=adjustment_tensors(None, W, H), adjust=Adjustment("invert"))
    plan = compile_plan([base, zero, full], (H, W))
    assert plan.skipped == {"z": "identity"} and plan.evaluated == ["base", "f"]
    torch.testing.assert_close(render(plan).image, 1.0 - base.tensors.color)


def test_a_clipped_adjustment_changes_only_its_base():
    # psd-tools' model: the clipped adjustment adjusts the base's colour (its alpha kept), then the base composes.
    torch.manual_seed(2)
    H, W = 5, 6
    bg = torch.rand(3, H, W, dtype=torch.float64)
    c, a = torch.rand(3, H, W, dtype=torch.float64), torch.rand(1, H, W, dtype=torch.float64)
    d = Document.from_dict(
        {
            "format": "lasagna.stack",
            "version": 1,
            "canvas": {"width": W, "height": H},
            "layers": [
                {"id": "bg", "kind": "pixels", "source": "layers/bg.png"},
                {"id": "base", "kind": "pixels", "source": "layers/base.png", "opacity": 0.9},
                {"id": "adj", "kind": "adjustment", "adjustment": {"type": "invert"}, "clip": True, "opacity": 0.6},
            ],
        }
    )
    stack = Stack(d, None, {"bg": LayerTensors(bg), "base": LayerTensors(c, a)})
    got = render_stack(stack, dtype=torch.float64).image
    adjusted = c + 0.6 * ((1 - c) - c)
    want = bg + 0.9 * a * (adjusted - bg)
    torch.testing.assert_close(got, want)


def test_layers_clipped_to_an_adjustment_paint_on_its_result():
    # psd-tools' model of an adjustment base: the clipped layers composite onto f(Cb), mixed by mask × opacity.
    torch.manual_seed(3)
    H, W = 5, 6
    bg = torch.rand(3, H, W, dtype=torch.float64)
    c, a = torch.rand(3, H, W, dtype=torch.float64), torch.rand(1, H, W, dtype=torch.float64)
    d = Document.from_dict(
        {
            "format": "lasagna.stack",
            "version": 1,
            "canvas": {"width": W, "height": H},
            "layers": [
                {"id": "bg", "kind": "pixels", "source": "layers/bg.png"},
                {"id": "adj", "kind": "adjustment", "adjustment": {"type": "invert"}, "opacity": 0.7},
                {"id": "top", "kind": "pixels", "source": "layers/top.png", "clip": True, "blend": "multiply"},
            ],
        }
    )
    stack = Stack(d, None, {"bg": LayerTensors(bg), "top": LayerTensors(c, a)})
    got = render_stack(stack, dtype=torch.float64).image
    t = 1 - bg
    t = t + a * (t * c - t)
    torch.testing.assert_close(got, bg + 0.7 * (t - bg))
