"""Gradient fills (``compose/gradient.py``), kornia's template: smoke, shapes, exceptions, a numpy float64 reference
written from the closed form of each style (not from our code), NaN behaviour, gradcheck in float64."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from lasagna.compose.gradient import STYLES, gradient_fill, ramp
from lasagna.document import Document
from lasagna.errors import DocumentError, LasagnaError
from lasagna.io.render import render_stack
from lasagna.io.stack import Stack
from lasagna.limits import MAX_GRADIENT_STOPS

STOPS = [
    {"location": 0.0, "color": [0.9, 0.1, 0.2], "midpoint": 0.3},
    {"location": 0.4, "color": [0.1, 0.8, 0.3], "midpoint": 0.5},
    {"location": 1.0, "color": [0.2, 0.3, 0.95], "midpoint": 0.7},
]
OPACITY = [{"location": 0.0, "opacity": 1.0, "midpoint": 0.5}, {"location": 1.0, "opacity": 0.25, "midpoint": 0.6}]


def reference_t(style, angle, scale, shift, box, viewport):
    """Closed form, pixel by pixel: the box's first pixel at −1 and last at +1 on each axis, divided by the scale
    length s (the side the ramp runs along, mixed by angle mod 90), then each style's z, clamped."""
    bw, bh = max(box[2] - box[0], 1), max(box[3] - box[1], 1)
    r = angle % 90.0
    s = scale / 100.0 * ((90 - r) / 90 * bw + r / 90 * bh)
    out = np.empty((viewport[3] - viewport[1], viewport[2] - viewport[0]))
    th = math.radians(angle % 360.0)
    for j in range(out.shape[0]):
        for i in range(out.shape[1]):
            px, py = viewport[0] + i - box[0], viewport[1] + j - box[1]
            u = (2.0 * px / (bw - 1) - 1.0 if bw > 1 else -1.0) - shift[0] / 50.0
            v = (2.0 * py / (bh - 1) - 1.0 if bh > 1 else -1.0) - shift[1] / 50.0
            X, Y = u * bw / s, v * bh / s
            a = X * math.cos(th) - Y * math.sin(th)  # along the ramp
            b = X * math.sin(th) + Y * math.cos(th)  # across it
            z = {
                "linear": (a + 1.0) / 2.0,
                "radial": math.hypot(X, Y),
                "angle": ((math.degrees(math.atan2(Y, X)) + angle) % 360.0) / 360.0,
                "reflected": abs(a),
                "diamond": abs(a) + abs(b),
            }[style]
            out[j, i] = min(max(z, 0.0), 1.0)
    return out


def reference_stops(t, stops, key):
    """Walk the stops: the segment holding t, its fraction bent so the start stop's midpoint is one half."""
    xs = [s["location"] for s in stops]
    vals = [np.atleast_1d(np.asarray(s[key], dtype=np.float64)) for s in stops]
    out = np.empty((len(vals[0]), *t.shape))
    for idx, x in np.ndenumerate(t):
        if x <= xs[0]:
            out[(slice(None), *idx)] = vals[0]
            continue
        if x >= xs[-1]:
            out[(slice(None), *idx)] = vals[-1]
            continue
        k = max(i for i in range(len(xs) - 1) if xs[i] <= x)
        u = (x - xs[k]) / (xs[k + 1] - xs[k])
        m = stops[k]["midpoint"]
        f = 0.5 * u / m if u <= m else 0.5 + 0.5 * (u - m) / (1 - m)
        out[(slice(None), *idx)] = vals[k] + f * (vals[k + 1] - vals[k])
    return out


class TestGradientFill:
    def test_smoke_and_shapes(self):
        color, alpha = gradient_fill({"stops": STOPS}, (0, 0, 7, 5), (0, 0, 7, 5))
        assert color.shape == (3, 5, 7) and alpha is None and color.dtype == torch.float32
        color, alpha = gradient_fill({"stops": STOPS, "opacity_stops": OPACITY}, (0, 0, 7, 5), (2, 1, 5, 4))
        assert color.shape == (3, 3, 3) and alpha.shape == (1, 3, 3)

    @pytest.mark.parametrize("style", STYLES)
    @pytest.mark.parametrize(
        "angle,scale,shift,box,viewport",
        [
            (90.0, 100.0, (0.0, 0.0), (0, 0, 9, 6), (0, 0, 9, 6)),
            (30.0, 75.0, (10.0, -20.0), (2, 1, 9, 8), (0, 0, 11, 9)),  # viewport larger than the box
            (-135.0, 250.0, (0.0, 5.0), (0, 0, 1, 5), (0, 0, 3, 5)),  # a box one pixel wide
        ],
    )
    def test_matches_the_closed_form(self, style, angle, scale, shift, box, viewport):
        p = {"style": style, "angle": angle, "scale": scale, "shift": shift, "reverse": style == "diamond"}
        p |= {"stops": STOPS, "opacity_stops": OPACITY}
        t = reference_t(style, angle, scale, shift, box, viewport)
        t = 1.0 - t if p["reverse"] else t
        color, alpha = gradient_fill(p, box, viewport, torch.float64)
        assert np.abs(color.numpy() - reference_stops(t, STOPS, "color")).max() < 1e-12
        assert np.abs(alpha.numpy() - reference_stops(t, OPACITY, "opacity")).max() < 1e-12

    def test_hard_edge_takes_the_later_stop(self):
        stops = [
            {"location": 0.0, "color": [0.0, 0.0, 0.0]},
            {"location": 0.5, "color": [1.0, 0.0, 0.0]},
            {"location": 0.5, "color": [0.0, 1.0, 0.0]},
            {"location": 1.0, "color": [0.0, 0.0, 1.0]},
        ]
        color, _ = gradient_fill({"angle": 0.0, "stops": stops}, (0, 0, 9, 1), (0, 0, 9, 1), torch.float64)
        assert color[:, 0, 4].tolist() == [0.0, 1.0, 0.0]  # t = ½ exactly: the stop after the edge

    def test_exceptions(self):
        box = (0, 0, 4, 4)
        with pytest.raises(LasagnaError, match="finite"):
            gradient_fill({"angle": float("nan"), "stops": STOPS}, box, box)
        with pytest.raises(LasagnaError, match="not sorted"):
            gradient_fill({"stops": STOPS[::-1]}, box, box)
        with pytest.raises(LasagnaError, match=f"expected 2 to {MAX_GRADIENT_STOPS}"):
            gradient_fill({"stops": STOPS * 100}, box, box)
        with pytest.raises(LasagnaError, match="unknown gradient style"):
            ramp("spiral", 0.0, 100.0, (0.0, 0.0), box, box)
        bad = [dict(STOPS[0], color=[float("nan"), 0.0, 0.0]), STOPS[1]]
        with pytest.raises(LasagnaError, match="NaN"):
            gradient_fill({"stops": bad}, box, box)

    def test_gradcheck_in_the_stop_colours_and_opacities(self):
        colors = torch.rand(3, 3, dtype=torch.float64, requires_grad=True)
        ops = torch.rand(2, dtype=torch.float64, requires_grad=True)

        def f(colors, ops):
            stops = [dict(s, color=colors[:, i]) for i, s in enumerate(STOPS)]
            opacity = [dict(s, opacity=ops[i]) for i, s in enumerate(OPACITY)]
            p = {"style": "radial", "stops": stops, "opacity_stops": opacity}
            return gradient_fill(p, (0, 0, 6, 5), (0, 0, 6, 5), torch.float64)

        assert torch.autograd.gradcheck(f, (colors, ops))


def _doc(layer: dict, background=(1.0, 1.0, 1.0)) -> dict:
    return {
        "format": "lasagna.stack",
        "version": 1,
        "canvas": {"width": 8, "height": 6, "background": list(background)},
        "layers": [layer],
    }


GRADIENT = {"style": "linear", "angle": 0.0, "stops": STOPS[::2]}


class TestGradientLayer:
    def test_a_layer_composites_its_fill_with_opacity_and_blend(self):
        layer = {"id": "g", "kind": "gradient", "blend": "multiply", "opacity": 0.5, "gradient": GRADIENT}
        image = render_stack(Stack(Document.from_dict(_doc(layer))), dtype=torch.float64).image.numpy()
        t = reference_t("linear", 0.0, 100.0, (0.0, 0.0), (0, 0, 8, 6), (0, 0, 8, 6))
        fill = reference_stops(t, STOPS[::2], "color")
        assert np.abs(image - (1.0 + 0.5 * (fill - 1.0))).max() < 1e-12

    def test_align_lays_the_ramp_on_the_layer_or_the_canvas(self):
        for align, box in ((True, (2, 1, 6, 4)), (False, (0, 0, 8, 6))):
            g = dict(GRADIENT, align=align)
            layer = {"id": "g", "kind": "gradient", "gradient": g, "offset": {"x": 2, "y": 1}}
            layer["size"] = {"width": 4, "height": 3}
            image = render_stack(Stack(Document.from_dict(_doc(layer))), dtype=torch.float64).image.numpy()
            fill = reference_stops(reference_t("linear", 0.0, 100.0, (0, 0), box, (2, 1, 6, 4)), STOPS[::2], "color")
            assert np.abs(image[:, 1:4, 2:6] - fill).max() < 1e-12 and (image[:, 0] == 1.0).all()

    @pytest.mark.parametrize(
        "change,message",
        [
            ({"angle": float("nan")}, "angle"),
            ({"stops": STOPS[::-1]}, "not sorted"),
            ({"stops": STOPS * 400_000}, f"at most {MAX_GRADIENT_STOPS}"),
            ({"style": "spiral"}, "style"),
            ({"scale": 0.0}, "scale"),
        ],
    )
    def test_bad_parameters_are_one_line(self, change, message):
        layer = {"id": "g", "kind": "gradient", "gradient": {**GRADIENT, **change}}
        with pytest.raises(DocumentError, match=message) as err:
            Document.from_dict(_doc(layer))
        assert "\n" not in str(err.value)

    def test_validate_refuses_bad_parameters_in_one_line_exit_2(self, tmp_path, capsys):
        from lasagna.cli import main

        stops = [{"location": 0.0, "color": [0.0, 0.0, 0.0]}] * 10_000  # within the file size limit, over the stops'
        for gradient in ({**GRADIENT, "stops": STOPS[::-1]}, {**GRADIENT, "stops": stops}):
            (tmp_path / "stack.json").write_text(
                json.dumps(_doc({"id": "g", "kind": "gradient", "gradient": gradient}))
            )
            assert main(["validate", str(tmp_path)]) == 2
            err = capsys.readouterr().err.strip()
            assert "\n" not in err and "layers[0].gradient.stops" in err
