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
from lasagna.export.surface_import import NAMED_FIELDS, SHADOW_REACH, map_name, restore_surfaces
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


def made_with(folder, light: str, source_light: str | None = None, **fields) -> Stack:
    """``made``'s stack with any of the layer's render fields (``Stack.set_light``'s)."""
    torch.manual_seed(5)
    stack = Stack.from_image((torch.rand(3, 48, 64) * 200 + 40).to(torch.uint8))
    stack.add_surface("shape", bump(), light, source_light=source_light, name="Shape", offset=(0, 0))
    stack.set_light("shape", light, **fields)
    stack.save(folder)
    return stack


# Layers no one-light Lambert fit reads back: their map's name carries the fields (`map_name`).
NAMED = {
    "shadows": {"light": "az=120,el=35", "shadows": 0.7, "shadow_depth": 3.0},
    "occlusion": {"light": "az=120,el=55", "occlusion": 0.8},
    "gloss": {"light": "az=120,el=55", "gloss": 0.6, "shininess": 12.0},
    "point light": {"light": "x=0.3,y=0.4,z=0.5"},
    "two lights": {"light": "az=120,el=55", "extra_lights": [{"light": "left", "intensity": 0.5}]},
    "coloured ratio": {"light": "az=10,el=40", "source_light": "left", "light_color": (1.0, 0.6, 0.3)},
    "shadowed ratio": {"light": "az=10,el=35", "source_light": "left", "shadows": 0.8, "shadow_depth": 3.0},
}


def _fields(layer) -> dict:
    return layer.model_dump(mode="json", include=set(NAMED_FIELDS))


@pytest.mark.parametrize("fmt", ["ora", "psd"])
@pytest.mark.parametrize("case", list(NAMED))
def test_a_layer_the_fit_cannot_read_comes_back_by_its_maps_name(tmp_path, fmt, case):
    """Shadows, occlusion, a highlight, a point light, two lights, a coloured or a shadowed relight ratio: the file's
    multiplier is no one-light Lambert rendering (the next test: without its name the fit does not read it), so
    the hidden map's name carries the layer's render fields; read back, the pair is one surface layer with every
    field as it was, rendering as the original (`assert_alike`), and re-lit it follows the original re-lit."""
    original = made_with(tmp_path / "s", **NAMED[case])
    layer = original.document.layer("shape")
    assert map_name(layer).startswith("Shape (normal map) {")
    warnings: list[str] = []
    back = read_back(tmp_path, fmt, warnings)
    assert warnings == []
    got = next(layer for layer in back.document.layers if layer.name == "Shape")
    assert got.kind == "surface" and _fields(got) == _fields(layer)
    assert not any("(normal map)" in other.name for other in back.document.layers)
    assert_alike(back, got.id, original)
    back.set_light(got.id, "az=300,el=50")
    original.set_light("shape", "az=300,el=50")
    assert_alike(back, got.id, original)
    back.save(tmp_path / "again")
    assert _fields(load_stack(tmp_path / "again").document.layer(got.id)) == _fields(back.document.layer(got.id))


@pytest.mark.parametrize("case", list(NAMED))
def test_without_its_name_the_fit_does_not_read_such_a_layer(tmp_path, case):
    """The same files with the fields cut from the map's name: the pixels are no one-light Lambert rendering, so the
    pair stays pixels with one line — what a named layer gives back is the name's, confirmed, not the fit's."""
    made_with(tmp_path / "s", **NAMED[case])
    assert main(["export", str(tmp_path / "s"), "--ora", str(tmp_path / "s.ora")]) == 0
    stack = import_ora(tmp_path / "s.ora", surfaces=False)
    hidden = next(layer for layer in stack.document.layers if layer.name.startswith("Shape (normal map) {"))
    renamed = [
        layer.model_copy(update={"name": "Shape (normal map)"}) if layer.id == hidden.id else layer
        for layer in stack.document.layers
    ]
    stack.document = stack.document.model_copy(update={"layers": renamed})
    warnings: list[str] = []
    restore_surfaces(stack, warnings.append, "test")
    assert len(warnings) == 1 and "'Shape'" in warnings[0]
    assert {layer.name: layer.kind for layer in stack.document.layers}["Shape"] == "pixels"


def assert_alike(back: Stack, id: str, original: Stack) -> None:
    """The surface layer ``id`` read back renders the original's multiplier y within 3.5 codes × max(1, y)² (the
    import's steps) away from its cast shadows, and on them and ``SHADOW_REACH`` traced pixels beside them within
    that of the range the original renders over that neighbourhood: the file's 8-bit map integrates to heights a
    little off the stored map's, so a shadow's soft edge may move. The multipliers, not the composites: the base's
    noise apart."""
    from lasagna.compose.surface import layer_surface_tensors

    layer = original.document.layer("shape")
    was = layer_surface_tensors(original.tensors["shape"], layer)[0].color
    flat = layer_surface_tensors(original.tensors["shape"], layer.model_copy(update={"shadows": 0.0}))[0].color
    reach = SHADOW_REACH * math.ceil(max(was.shape[-2:]) / 512)  # traced pixels (`SHADOW_MAX_SIDE`), in the map's
    k = 2 * reach + 1

    def pool(x):
        return torch.nn.functional.max_pool2d(torch.nn.functional.pad(x, (reach,) * 4, mode="replicate"), k, 1)

    near = pool(((flat - was).abs() > 0.5 / 255).amax(0, keepdim=True).double()[None])[0, 0] > 0
    now = layer_surface_tensors(back.tensors[id], back.document.layer(id))[0].color
    steps = was.clamp_min(1.0) ** 2  # a ratio above 1 is a multiply and colour-dodge pair: steps grow as y²
    assert float(((now - was).abs() / steps).amax(0)[~near].max()) <= 3.5 / 255
    hi, lo = pool(was[None])[0], -pool(-was[None])[0]
    outside = (torch.maximum(lo - now, now - hi).clamp_min(0) / steps).amax(0)
    assert not bool(near.any()) or float(outside[near].max()) <= 3.5 / 255


def test_a_deep_shadows_edge_may_move_a_pixel(tmp_path):
    """A deep relief with long shadows: the file's 8-bit map integrates to heights a little off the stored map's,
    and a shadow's soft edge moves (more than ten codes at a pixel). The layer still comes back, its shadow at most a
    pixel from the original's (`assert_alike`)."""
    original = made_with(tmp_path / "s", "az=120,el=60", shadows=1.0, shadow_depth=3.0, relief=1.5)
    warnings: list[str] = []
    back = read_back(tmp_path, "ora", warnings)
    got = next(layer for layer in back.document.layers if layer.name == "Shape")
    assert warnings == [] and got.kind == "surface" and got.shadows == 1.0 and got.relief == 1.0  # relief in map
    assert float((back.render().image - original.render().image).abs().max()) > 10 / 255  # an edge did move
    assert_alike(back, got.id, original)


def test_a_steep_reliefs_shadows_need_a_16_bit_map(tmp_path):
    """Boxes on a ground (steps, which a normal map holds as its steepest slopes): integrated from an 8-bit map, their
    heights are far enough off the 16-bit map's that long shadows move by many pixels — the ORA's pair stays pixels,
    and its line names the cure; a PSD written with ``--depth 16`` carries the map whole and the layer comes back."""
    rows, cols = torch.meshgrid(torch.linspace(0, 1, 128), torch.linspace(0, 1, 128), indexing="ij")
    height = 0.12 * ((cols - 0.3).abs() < 0.1) * ((rows - 0.4).abs() < 0.12) + 0.2 * ((cols - 0.7).abs() < 0.06)
    stack = Stack.from_image(torch.full((3, 128, 128), 0.7))
    stack.add_surface("shape", normals_from_height(height[None, None])[0], "az=200,el=70", name="Shape")
    stack.set_light("shape", "az=200,el=70", shadows=0.8)
    stack.save(tmp_path / "s")
    warnings: list[str] = []
    back = read_back(tmp_path, "ora", warnings)
    assert next(layer for layer in back.document.layers if layer.name == "Shape").kind == "pixels"
    assert len(warnings) == 1 and "8-bit normal map" in warnings[0] and "--depth 16" in warnings[0]
    assert main(["export", str(tmp_path / "s"), "--psd", str(tmp_path / "d.psd"), "--depth", "16"]) == 0
    warnings.clear()
    deep = read_psd(tmp_path / "d.psd", warn=warnings.append)
    got = next(layer for layer in deep.document.layers if layer.name == "Shape")
    assert warnings == [] and got.kind == "surface" and got.shadows == 0.8
    assert_alike(deep, got.id, stack)


def test_a_map_larger_than_the_trace_comes_back_with_its_shadows(tmp_path):
    """A 200 × 1100 map: its shadows are traced at 512 across and enlarged, so a shadow's edge moves by up to a traced
    pixel, about two of the map's; the layer still comes back (it stayed pixels while the slack was one map pixel)."""
    torch.manual_seed(5)
    original = Stack.from_image((torch.rand(3, 200, 1100) * 200 + 40).to(torch.uint8))
    original.add_surface("shape", bump(200, 1100), "az=120,el=60", name="Shape", offset=(0, 0))
    original.set_light("shape", "az=120,el=60", shadows=1.0, shadow_depth=3.0, relief=1.5)
    original.save(tmp_path / "s")
    warnings: list[str] = []
    back = read_back(tmp_path, "ora", warnings)
    got = next(layer for layer in back.document.layers if layer.name == "Shape")
    assert warnings == [] and got.kind == "surface"
    assert_alike(back, got.id, original)


@pytest.mark.parametrize(
    ("note", "why"),
    [
        ("{nonsense", "not the light fields"),
        ('{"light":' + "[" * 100_000, "not the light fields"),  # deeper than json's recursion
        ('{"light":"left","colour":"red"}', "not the light fields"),
        ('{"light":"left","shadows":2}', "no surface layer takes"),
        ('{"light":"left","shadows":0.3}', "codes off"),
    ],
)
def test_a_map_name_that_is_not_ours_keeps_the_pair_pixels(tmp_path, note, why):
    """A name that holds no fields we wrote, fields no layer takes, or a light whose render is not the file's
    multiplier (here the pixels were rendered under another light): one line naming the layer and why."""
    made_with(tmp_path / "s", "az=120,el=60", shadows=0.7, shadow_depth=3.0)
    assert main(["export", str(tmp_path / "s"), "--ora", str(tmp_path / "s.ora")]) == 0
    stack = import_ora(tmp_path / "s.ora", surfaces=False)
    renamed = [
        layer.model_copy(update={"name": f"Shape (normal map) {note}"}) if layer.name.startswith("Shape (") else layer
        for layer in stack.document.layers
    ]
    stack.document = stack.document.model_copy(update={"layers": renamed})
    warnings: list[str] = []
    restore_surfaces(stack, warnings.append, "test")
    assert len(warnings) == 1 and "'Shape'" in warnings[0] and why in warnings[0]
    assert {layer.name: layer.kind for layer in stack.document.layers}["Shape"] == "pixels"


def test_a_name_cut_at_255_characters_says_so(tmp_path):
    """Eight extra lights need a 600-character name; GIMP saves a PSD's names cut at 255: the pair stays pixels and
    the line says the name was cut (the PSD written by us keeps the whole name in its Unicode block)."""
    extras = [{"light": f"az={30 * i},el=50", "intensity": 0.1, "color": [1.0, 0.9, 0.8]} for i in range(8)]
    made_with(tmp_path / "s", "az=120,el=35", extra_lights=extras)
    back = read_back(tmp_path, "psd", [])
    assert next(layer for layer in back.document.layers if layer.name == "Shape").kind == "surface"
    stack = read_psd(tmp_path / "s.psd", surfaces=False)
    hidden = next(layer for layer in stack.document.layers if layer.name.startswith("Shape (normal map) {"))
    assert len(hidden.name) > 255
    renamed = [
        layer.model_copy(update={"name": layer.name[:255]}) if layer.id == hidden.id else layer
        for layer in stack.document.layers
    ]
    stack.document = stack.document.model_copy(update={"layers": renamed})
    warnings: list[str] = []
    restore_surfaces(stack, warnings.append, "test")
    assert len(warnings) == 1 and "cut at 255 characters" in warnings[0]


def test_a_shadows_slack_takes_only_what_a_shadow_could_render():
    """A 2×2 map whose render spans four orders of magnitude (a relight ratio at ambient 10⁻⁴) with random pixels over
    it: every pixel is beside a shadow, and the neighbourhood's values span the pixels' — but no shadow brightens, and
    none darkens a pixel below (1 − s) of its unshadowed render, so the pair stays pixels (it was taken before the
    slack was bounded so)."""
    torch.manual_seed(2)
    stack = Stack.from_image(torch.full((3, 2, 2), 0.5))
    note = '{"light":"left","source_light":"right","ambient":0.0001,"shadows":1}'
    stack.add_layer("map", torch.rand(3, 2, 2), name=f"S (normal map) {note}", visible=False)
    stack.add_layer("s", torch.rand(1, 2, 2), name="S", blend="multiply")
    warnings: list[str] = []
    restore_surfaces(stack, warnings.append, "test")
    assert stack.document.layer("s").kind == "pixels" and len(warnings) == 1 and "codes off" in warnings[0]


@pytest.mark.parametrize("fmt", ["ora", "psd"])
def test_a_layer_the_canvas_cuts_comes_back_whole(tmp_path, fmt):
    """A surface layer hanging off the canvas's top-left, lit by a spot with a point extra light and casting shadows:
    the file holds the multiplier's part on the canvas and the normal map whole, so the layer comes back whole — its
    place, its size, its lights as they were — and renders as the original (`assert_alike`) over the whole layer,
    off the canvas too (its shadows traced over the whole map, as the original's are)."""
    torch.manual_seed(5)
    stack = Stack.from_image((torch.rand(3, 48, 64) * 200 + 40).to(torch.uint8))
    spot = "x=0.6,y=0.5,z=0.4,cone=40,ax=0.5,ay=0.6"
    stack.add_surface("shape", bump(), spot, name="Shape", offset=(-16, -8))
    stack.set_light("shape", spot, extra_lights=[{"light": "x=0.9,y=0.9,z=0.2", "intensity": 0.5}], shadows=0.8)
    stack.save(tmp_path / "s")
    warnings: list[str] = []
    back = read_back(tmp_path, fmt, warnings)
    got = next(layer for layer in back.document.layers if layer.name == "Shape")
    assert warnings == [] and got.kind == "surface" and (got.offset.x, got.offset.y) == (-16, -8)
    assert tuple(back.tensors[got.id].color.shape) == (3, 48, 64)
    assert _fields(got) == _fields(stack.document.layer("shape"))
    assert_alike(back, got.id, stack)  # the whole layer, off the canvas too


def test_paint_over_a_named_layer_keeps_it_pixels(tmp_path):
    """A stroke ten codes bright over a shadowed layer's multiplier (its map's name intact): the pair stays pixels."""
    made_with(tmp_path / "s", "az=120,el=60", shadows=0.7, shadow_depth=3.0)
    assert main(["export", str(tmp_path / "s"), "--ora", str(tmp_path / "s.ora")]) == 0
    stack = import_ora(tmp_path / "s.ora", surfaces=False)
    shape = next(layer for layer in stack.document.layers if layer.name == "Shape")
    stack.tensors[shape.id].color[:, 20:30, 20:30] = (stack.tensors[shape.id].color[:, 20:30, 20:30] - 10 / 255).clamp(
        min=0
    )
    warnings: list[str] = []
    restore_surfaces(stack, warnings.append, "test")
    assert len(warnings) == 1 and "codes off (paint over it" in warnings[0]


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
    from lasagna.export.light_fit import fit_ratio, fit_shading

    n = bump().double().numpy()
    fit = fit_shading(n, lambert64(n, az, el, a, k))
    assert fit is not None
    got = np.asarray(unit_vector(*fit["light"]))
    assert math.degrees(math.acos(min(1.0, float(got @ np.asarray(unit_vector(az, el)))))) < 0.05
    assert abs(fit["ambient"] - a) < 1e-4 and abs(fit["light_intensity"] - k) < 1e-4
    apart = float(np.asarray(unit_vector(az, el)) @ np.asarray(unit_vector(az_s, el_s)))
    assume(apart < math.cos(math.radians(10)))  # one light over itself is a ratio of one: no light to read
    ratio = lambert64(n, az, el, a, 1.0) / lambert64(n, az_s, el_s, a, 1.0)
    fit = fit_ratio(n, ratio)
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


@pytest.mark.parametrize("reach", [1, 2, 8])
def test_the_separable_neighbourhood_maximum_is_the_square_ones(reach):
    """The shadows' slack takes each pixel's (2·reach + 1)² neighbourhood maximum by two running maxima (rows, then
    columns): equal, bit for bit, to the square window's, edges replicated."""
    from lasagna.export.surface_import import _pool

    x = torch.rand(2, 3, 37, 53, dtype=torch.float64, generator=torch.Generator().manual_seed(reach))
    padded = torch.nn.functional.pad(x, (reach,) * 4, mode="replicate")
    assert torch.equal(_pool(x, reach), torch.nn.functional.max_pool2d(padded, 2 * reach + 1, stride=1))
