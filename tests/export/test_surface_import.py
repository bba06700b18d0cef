"""A surface layer read back from OpenRaster and PSD (`lasagna.export.surface_import`): the rendered multiplier over
its hidden normal map is made one surface layer again when the pixels are one light's rendering of the map, and
kept as pixels, with one warning line, when they are not. References: the light the stack was made with (the
world's truth), numpy float64 Lambert of the map the file holds."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from lasagna.cli import main
from lasagna.compose.surface import normals_from_height
from lasagna.document.condition import unit_vector
from lasagna.export import import_ora
from lasagna.export.psd_import import read_psd
from lasagna.export.surface_import import restore_surfaces
from lasagna.io.stack import Stack, load_stack


def bump(h: int = 48, w: int = 64) -> torch.Tensor:
    """Unit normals (3, h, w) of a smooth bump and a ridge: every facing, none flat over most of the map."""
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1.4, 1.4, w), indexing="ij")
    height = 0.6 * torch.exp(-(xx**2 + yy**2) * 2) + 0.15 * torch.sin(3 * xx)
    return normals_from_height(height[None, None])[0]


def made(folder, light="az=120,el=55", **fields) -> Stack:
    torch.manual_seed(5)
    base = (torch.rand(3, 48, 64) * 200 + 40).to(torch.uint8)
    stack = Stack.from_image(base)
    relight = {k: fields.pop(k) for k in ("gloss", "light_color", "shadows") if k in fields}
    stack.add_surface("shape", bump(), light, name="Shape", offset=(0, 0), **fields)
    if relight:
        stack.set_light("shape", light, **relight)
    stack.save(folder)
    return stack


def read_back(tmp_path, fmt: str, warnings: list[str]) -> Stack:
    assert main(["export", str(tmp_path / "s"), f"--{fmt}", str(tmp_path / f"s.{fmt}")]) == 0
    path = tmp_path / f"s.{fmt}"
    return import_ora(path, warn=warnings.append) if fmt == "ora" else read_psd(path, warn=warnings.append)


CASES = [
    ({"light": "az=120,el=55"}, {"light": "az=120,el=55", "ambient": 0.25, "light_intensity": 1.0}),
    ({"light": "top-left", "ambient": 0.3}, {"light": "top-left", "ambient": 0.3, "source_light": None}),
    ({"light": "az=10,el=55", "source_light": "left"}, {"light": "az=10,el=55", "source_light": "left"}),
]


@pytest.mark.parametrize("fmt", ["ora", "psd"])
@pytest.mark.parametrize(("fields", "want"), CASES)
def test_a_surface_layer_comes_back_as_one_surface_lit_as_it_was(tmp_path, fmt, fields, want):
    """Shading and a relight ratio (above 1: a multiply and colour-dodge pair in the file), through ORA and PSD: one
    surface layer with the multiplier's name and place (an ORA's id too), the same light fields, no hidden map left;
    its render within 3.5 codes of the original (a PSD's 8-bit map), and re-lit it follows the original re-lit."""
    original = made(tmp_path / "s", **dict(fields))
    warnings: list[str] = []
    back = read_back(tmp_path, fmt, warnings)
    assert warnings == []
    layer = next(layer for layer in back.document.layers if layer.name == "Shape")  # a PSD's ids are its names
    assert layer.kind == "surface" and layer.id == ("shape" if fmt == "ora" else "Shape")
    for key, value in want.items():
        assert getattr(layer, key) == value, key
    assert not any(other.name.endswith("(normal map)") for other in back.document.layers)
    diff = (back.render().image - original.render().image).abs().max()
    assert float(diff) <= 3.5 / 255
    back.set_light(layer.id, "az=300,el=40")
    original.set_light("shape", "az=300,el=40")
    assert float((back.render().image - original.render().image).abs().max()) <= 3.5 / 255
    back.save(tmp_path / "again")  # what we read, we write
    assert load_stack(tmp_path / "again").document.layer(layer.id).kind == "surface"


@pytest.mark.parametrize(
    ("fields", "why"),
    [
        ({"gloss": 0.6}, "codes off"),
        ({"light_color": (1.0, 0.6, 0.3), "source_light": "left"}, "no light fits"),
    ],
)
def test_a_layer_no_single_light_renders_stays_pixels_with_one_line(tmp_path, fields, why):
    """A highlight, or a coloured light in a relight ratio (its source white), is no one-light Lambert rendering the
    fit reads: the pair stays as it was read, one warning line naming the layer and why."""
    made(tmp_path / "s", **fields)
    warnings: list[str] = []
    back = read_back(tmp_path, "ora", warnings)
    assert len(warnings) == 1 and "'Shape'" in warnings[0] and why in warnings[0]
    kinds = {layer.name: layer.kind for layer in back.document.layers}
    assert kinds["Shape"] == "pixels" and kinds["Shape (normal map)"] == "pixels"


def test_paint_over_the_multiplier_keeps_it_pixels(tmp_path):
    """A stroke over the rendered multiplier (ten codes brighter in a square) is kept: the pair stays pixels."""
    made(tmp_path / "s")
    back = read_back(tmp_path, "ora", [])
    assert back.document.layer("shape").kind == "surface"
    painted = load_stack(tmp_path / "s")
    from lasagna.compose.surface import layer_surface_tensors

    rendered = layer_surface_tensors(painted.tensors["shape"], painted.document.layer("shape"))[0].color.clone()
    rendered[:, 10:20, 10:20] = (rendered[:, 10:20, 10:20] + 10 / 255).clamp(max=1)
    normal_codes = painted.tensors["shape"].color
    stack = Stack.from_image(painted.tensors["base"].color)
    stack.add_layer("map", normal_codes, name="Shape (normal map)", visible=False)
    stack.add_layer("shape", rendered, name="Shape", blend="multiply")
    warnings: list[str] = []
    restore_surfaces(stack, warnings.append, "test")
    assert stack.document.layer("shape").kind == "pixels" and len(warnings) == 1 and "codes off" in warnings[0]
    stack = Stack.from_image(painted.tensors["base"].color)  # the same pair unpainted is restored
    stack.add_layer("map", normal_codes, name="Shape (normal map)", visible=False)
    clean = layer_surface_tensors(painted.tensors["shape"], painted.document.layer("shape"))[0].color
    stack.add_layer("shape", clean, name="Shape", blend="multiply")
    restore_surfaces(stack, warnings.append, "test")
    assert stack.document.layer("shape").kind == "surface" and list(stack.document.ids) == ["base", "shape"]


def lambert64(n: np.ndarray, az: float, el: float, a: float, k: float) -> np.ndarray:
    return a + (1 - a) * k * np.maximum(0.0, np.einsum("chw,c->hw", n, unit_vector(az, el)))


@settings(max_examples=25, deadline=None)
@given(
    az=st.floats(0, 359.9),
    el=st.floats(5, 70),
    a=st.floats(0.05, 0.6),
    k=st.floats(0.5, 2.0),
    az_s=st.floats(0, 359.9),
    el_s=st.floats(5, 70),
)
def test_the_fits_recover_the_light_of_exact_renders(az, el, a, k, az_s, el_s):
    """Property: the shading fit of a float64 Lambert render returns its light (within 0.05°), ambient and intensity
    (within 10⁻⁴); the ratio fit of S(l)/S(l_s), the lights 10° or more apart, returns both lights and the ambient."""
    from lasagna.export.surface_import import _fit_ratio, _fit_shading

    n = bump().double().numpy()
    fit = _fit_shading(n, lambert64(n, az, el, a, k))
    assert fit is not None
    got = np.asarray(unit_vector(*fit["light"]))
    assert math.degrees(math.acos(min(1.0, float(got @ np.asarray(unit_vector(az, el)))))) < 0.05
    assert abs(fit["ambient"] - a) < 1e-4 and abs(fit["light_intensity"] - k) < 1e-4
    apart = float(np.asarray(unit_vector(az, el)) @ np.asarray(unit_vector(az_s, el_s)))
    assume(apart < math.cos(math.radians(10)))  # one light over itself is a ratio of one: no light to read
    ratio = lambert64(n, az, el, a, 1.0) / lambert64(n, az_s, el_s, a, 1.0)
    fit = _fit_ratio(n, ratio)
    assert fit is not None
    for light, (taz, tel) in ((fit["light"], (az, el)), (fit["source_light"], (az_s, el_s))):
        cos = float(np.asarray(unit_vector(*light)) @ np.asarray(unit_vector(taz, tel)))
        assert math.degrees(math.acos(min(1.0, cos))) < 0.05
    assert abs(fit["ambient"] - a) < 1e-4


@pytest.mark.parametrize("fmt", ["ora", "psd"])
def test_cli_import_makes_the_surface_again_unless_as_pixels(tmp_path, fmt, capsys):
    """`lasagna import-ora` / `import-psd`: the pair is one surface layer in the stack written; ``--as-pixels`` keeps
    the two pixel layers the file holds."""
    import json

    made(tmp_path / "s")
    assert main(["export", str(tmp_path / "s"), f"--{fmt}", str(tmp_path / f"s.{fmt}")]) == 0
    command = f"import-{fmt}"
    assert main([command, str(tmp_path / f"s.{fmt}"), "-o", str(tmp_path / "back")]) == 0
    kinds = {
        layer["name"]: layer["kind"] for layer in json.loads((tmp_path / "back" / "stack.json").read_text())["layers"]
    }
    assert kinds["Shape"] == "surface" and "Shape (normal map)" not in kinds
    assert main([command, str(tmp_path / f"s.{fmt}"), "-o", str(tmp_path / "px"), "--as-pixels"]) == 0
    kinds = {
        layer["name"]: layer["kind"] for layer in json.loads((tmp_path / "px" / "stack.json").read_text())["layers"]
    }
    assert kinds["Shape"] == "pixels" and kinds["Shape (normal map)"] == "pixels"


@pytest.mark.parametrize("fmt", ["ora", "psd"])
def test_a_surface_layer_inside_a_group_comes_back_inside_it(tmp_path, fmt):
    """The pair is found at any depth: a surface layer in an isolated group is one surface layer in that group."""
    stack = made(tmp_path / "plain", light="az=200,el=40")
    stack.document = stack.document.grouped(["shape"], {"id": "g", "kind": "group", "name": "G", "isolated": True})
    stack.save(tmp_path / "s")
    warnings: list[str] = []
    back = read_back(tmp_path, fmt, warnings)
    group = next(layer for layer in back.document.layers if layer.kind == "group")
    assert warnings == [] and [(c.name, c.kind, c.light) for c in group.layers] == [
        ("Shape", "surface", "az=200,el=40")
    ]
    assert float((back.render().image - stack.render().image).abs().max()) <= 3.5 / 255


def test_a_map_that_cannot_tell_its_light_stays_pixels(tmp_path):
    """A flat map under any light renders one value: no light is read into it (one line, the pair kept)."""
    stack = Stack.from_image(torch.full((3, 16, 16), 0.5))
    stack.add_layer(
        "map",
        torch.full((3, 16, 16), 0.5).index_fill(0, torch.tensor([2]), 1.0),
        name="Flat (normal map)",
        visible=False,
    )
    stack.add_layer("flat", torch.full((1, 16, 16), 0.625), name="Flat", blend="multiply")
    warnings: list[str] = []
    restore_surfaces(stack, warnings.append, "test")
    assert stack.document.layer("flat").kind == "pixels" and len(warnings) == 1 and "no light fits" in warnings[0]


def test_a_painted_clamp_layer_keeps_the_psd_pair_pixels(tmp_path):
    """A PSD holds a ratio above 1 as multiply, colour dodge and a white darken clamp; the clamp is dropped only while
    it is white (the identity it was written as): painted on, the layers stay as read, one line."""
    made(tmp_path / "s", light="az=10,el=55", source_light="left")
    assert main(["export", str(tmp_path / "s"), "--psd", str(tmp_path / "s.psd")]) == 0
    for painted in (False, True):
        stack = read_psd(tmp_path / "s.psd", surfaces=False)
        clamp = next(layer for layer in stack.document.layers if layer.name.endswith("(clamp to 1)"))
        if painted:
            stack.tensors[clamp.id].color[:, 3:6, 3:6] = 0.5
        warnings: list[str] = []
        restore_surfaces(stack, warnings.append, "test")
        kinds = {layer.name: layer.kind for layer in stack.document.layers}
        if painted:
            assert kinds["Shape"] == "pixels" and len(warnings) == 1 and "clamp" in warnings[0]
        else:
            assert kinds["Shape"] == "surface" and warnings == [] and clamp.name not in kinds


@pytest.mark.parametrize("fmt", ["ora", "psd"])
def test_a_coloured_light_comes_back_with_its_colour(tmp_path, fmt):
    """A coloured light's shading (three channels, one light): each channel fitted, the fits agreeing on the light,
    the layer comes back with the light, its colour within 0.01 and its intensity, rendering within 3.5 codes."""
    original = made(tmp_path / "s", light="az=150,el=50", light_color=(1.0, 0.6, 0.3))
    warnings: list[str] = []
    back = read_back(tmp_path, fmt, warnings)
    layer = next(layer for layer in back.document.layers if layer.name == "Shape")
    assert warnings == [] and layer.kind == "surface" and layer.light == "az=150,el=50"
    np.testing.assert_allclose(layer.light_color, (1.0, 0.6, 0.3), atol=0.01)
    assert abs(layer.light_intensity - 1.0) < 0.01 and layer.ambient == 0.25
    assert float((back.render().image - original.render().image).abs().max()) <= 3.5 / 255
