"""Surface layers in a stack folder: a 16-bit normal map lit by the layer's light, against an independent numpy
float64 reading of the PNG (pypng) and the shading formula; re-lit exactly by editing stack.json."""

from __future__ import annotations

import json
import math

import jsonschema
import numpy as np
import png
import pytest
import torch

from lasagna.compose.surface import normals_from_height
from lasagna.document import Document
from lasagna.errors import DocumentError
from lasagna.io.stack import Stack, load_stack

ROOT_SCHEMA = json.loads(open("schemas/stack.schema.json", encoding="utf-8").read())


def light(az: float, el: float) -> np.ndarray:
    a, e = math.radians(az), math.radians(el)
    return np.array([math.sin(e) * math.cos(a), math.sin(e) * math.sin(a), math.cos(e)])


def read_normals(path) -> np.ndarray:
    """The normal map as unit vectors (3, h, w), float64, read with pypng: n = 2v − 1, renormalised."""
    w, h, rows, info = png.Reader(filename=str(path)).read()
    assert info["bitdepth"] == 16 and info["planes"] == 3
    v = np.array([list(r) for r in rows], dtype=np.float64).reshape(h, w, 3).transpose(2, 0, 1) / 65535.0
    n = 2 * v - 1
    return n / np.linalg.norm(n, axis=0, keepdims=True)


def shading(n: np.ndarray, l_vec: np.ndarray, a: float = 0.25) -> np.ndarray:
    return a + (1 - a) * np.maximum(0.0, np.einsum("chw,c->hw", n, l_vec))


def _largest_multiplier(stack) -> float:
    """The largest value of any surface layer's rendered multiplier in ``stack``."""
    from lasagna.compose.surface import layer_surface_tensors

    return max(
        float(layer_surface_tensors(stack.tensors[layer.id], layer)[0].color.max())
        for layer in stack.document.layers
        if layer.kind == "surface"
    )


def assert_files_flatten(stack, folder) -> None:
    """``stack`` saved to ``folder`` and exported: our ORA reader keeping the file's pixels (1.5/255) and psd-tools,
    an independent one (2.5/255; where a multiplier exceeds 1, through the file's exact composite), flatten it to its
    composite; read back as surfaces, each restored layer renders within the restoring check's bound, three codes
    times max(1, y)² of its multiplier y (`lasagna.export.surface_import.MATCH_TOLERANCE`)."""
    from psd_tools import PSDImage

    from lasagna.cli import main
    from lasagna.export import import_ora
    from lasagna.export.surface_import import MATCH_TOLERANCE

    stack.save(folder)
    ora, psd = folder.with_suffix(".ora"), folder.with_suffix(".psd")
    assert main(["export", str(folder), "--ora", str(ora), "--psd", str(psd)]) == 0
    ours = stack.render().image.double().numpy()
    np.testing.assert_allclose(import_ora(ora, surfaces=False).render().image.double().numpy(), ours, atol=1.5 / 255)
    back = import_ora(ora, warn=lambda line: None)
    bound = MATCH_TOLERANCE * max(1.0, _largest_multiplier(stack)) ** 2 + 0.5 / 255
    np.testing.assert_allclose(back.render().image.double().numpy(), ours, atol=bound)
    flat = np.asarray(PSDImage.open(psd).composite(force=True).convert("RGB"), dtype=np.float64)
    np.testing.assert_allclose(flat.transpose(2, 0, 1) / 255, ours, atol=2.5 / 255)


@pytest.fixture
def stack():
    torch.manual_seed(0)
    base = (torch.rand(3, 12, 16) * 255).to(torch.uint8)  # stored codes: saved and reloaded exactly
    s = Stack.from_image(base)
    s.add_surface("shape", normals_from_height(0.08 * torch.randn(1, 1, 12, 16))[0], "left")
    return s


def test_composite_is_the_base_times_the_lambert_shading_of_the_stored_map(stack, tmp_path):
    stack.save(tmp_path)
    doc = json.loads((tmp_path / "stack.json").read_text())
    assert doc["layers"][1]["kind"] == "surface" and doc["layers"][1]["blend"] == "multiply"
    n = read_normals(tmp_path / doc["layers"][1]["source"])
    base = stack.tensors["base"].color.double().numpy()
    for light_text, (az, el) in (("left", (180, 60)), ("az=33.5,el=12", (33.5, 12))):
        stack.set_light("shape", light_text)
        ref = np.clip(base * shading(n, light(az, el))[None], 0, 1)
        np.testing.assert_allclose(stack.render().image.double().numpy(), ref, atol=2e-6)


def test_relight_ratio(stack):
    stack.set_light("shape", "right", source_light="left")
    n = stack.tensors["shape"].color.double().numpy() * 2 - 1
    n /= np.linalg.norm(n, axis=0, keepdims=True)
    ratio = shading(n, light(0, 60)) / shading(n, light(180, 60))
    base = stack.tensors["base"].color.double().numpy()
    np.testing.assert_allclose(stack.render().image.double().numpy(), np.clip(base * ratio, 0, 1), atol=2e-6)


def test_editing_the_light_in_stack_json_relights_bit_for_bit(stack, tmp_path):
    before = stack.render().image
    stack.save(tmp_path)
    assert torch.equal(load_stack(tmp_path).render().image, before)  # the saved map is what was rendered
    doc = json.loads((tmp_path / "stack.json").read_text())
    doc["layers"][1]["light"] = "az=250,el=35"
    (tmp_path / "stack.json").write_text(json.dumps(doc))
    stack.set_light("shape", "az=250,el=35")
    after = load_stack(tmp_path).render().image
    assert torch.equal(after, stack.render().image) and not torch.equal(after, before)


def test_cli_composite_and_exports(stack, tmp_path, capsys):
    from lasagna.cli import main

    stack.save(tmp_path / "s")
    assert main(["composite", str(tmp_path / "s")]) == 0
    assert (
        main(["export", str(tmp_path / "s"), "--ora", str(tmp_path / "s.ora"), "--psd", str(tmp_path / "s.psd")]) == 0
    )
    # The ORA's layer is the rendered multiplier, not the map: the file flattens to the composite; read back, the
    # multiplier over its hidden map is the surface layer again (tests/export/test_surface_import.py).
    from lasagna.export.ora_import import import_ora, read_ora

    _, _, layers = read_ora(tmp_path / "s.ora")
    assert {layer["name"]: layer["blend"] for layer in layers}["shape"] == "multiply"
    back = import_ora(tmp_path / "s.ora")
    assert back.document.layer("shape").kind == "surface"
    np.testing.assert_allclose(
        back.render().image.double().numpy(), stack.render().image.double().numpy(), atol=1.5 / 255
    )


VALID = {
    "format": "lasagna.stack",
    "version": 1,
    "canvas": {"width": 4, "height": 4},
    "layers": [
        {"id": "base", "kind": "pixels", "source": "layers/base.png"},
        {"id": "s", "kind": "surface", "blend": "multiply", "source": "layers/s.png", "light": "top-left"},
    ],
}


def test_an_elevation_of_90_is_refused_by_the_model():
    doc = json.loads(json.dumps(VALID))
    doc["layers"][1]["light"] = "az=0,el=90"  # the schema checks the text's form; the model its range
    with pytest.raises(DocumentError, match=r"layers\[1\]\.light"):
        Document.from_dict(doc)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"light": "upward"}, r"layers\[1\]\.light: expected one of left"),
        ({"light": "az=1;el=2"}, r"layers\[1\]\.light"),
        ({"blend": "normal"}, r"layers\[1\]\.blend: surface layer 's' has blend 'normal'"),
        ({"source_light": "left", "ambient": 0.0}, r"layers\[1\]\.ambient: .* expected ambient > 0"),
        ({"ambient": 1.0}, r"layers\[1\]\.ambient"),
        ({"range": [0, 2]}, r"layers\[1\]\.range"),
    ],
)
def test_bad_surface_layers_are_refused_by_the_model_and_the_schema(change, message):
    doc = json.loads(json.dumps(VALID))
    doc["layers"][1].update(change)
    with pytest.raises(DocumentError, match=message):
        Document.from_dict(doc)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(doc, ROOT_SCHEMA)


def test_a_valid_surface_layer_passes_both():
    Document.from_dict(VALID)
    jsonschema.validate(VALID, ROOT_SCHEMA)
    ratio = json.loads(json.dumps(VALID))
    ratio["layers"][1].update(source_light="az=10,el=50", ambient=0.1)
    Document.from_dict(ratio)
    jsonschema.validate(ratio, ROOT_SCHEMA)


def test_add_surface_refuses_bad_normals():
    s = Stack.from_image(torch.rand(3, 4, 4))
    with pytest.raises(Exception, match=r"normals have shape \(1, 4, 4\); expected \(3, h, w\)"):
        s.add_surface("x", torch.zeros(1, 4, 4), "left")
    assert s.ids == ("base",)


def test_export_normal_map_is_the_stored_map_on_the_canvas(stack, tmp_path, capsys):
    from lasagna.cli import main

    stack.save(tmp_path / "s")
    assert main(["export", str(tmp_path / "s"), "--normal-map", str(tmp_path / "n.png")]) == 0
    stored = read_normals(tmp_path / "s" / "layers" / "shape.png")
    exported = read_normals(tmp_path / "n.png")
    np.testing.assert_array_equal(exported, stored)
    assert main(["export", str(tmp_path / "s"), "--normal-map", str(tmp_path / "m.png"), "--surface", "base"]) == 2
    assert "no surface layer 'base'; expected one of shape" in capsys.readouterr().err


def test_export_normal_map_directx_flips_green_and_reads_back(stack, tmp_path, capsys):
    """``--directx`` writes the map +Y down: red and blue the OpenGL map's codes, green 65535 − its code, exactly;
    ``lasagna add-surface --directx`` reads it back to the layer the OpenGL map gives, bit for bit (within a 16-bit
    code of the original: add-surface's float32 normals). ``--directx`` alone is one line and exit 2."""
    from lasagna.cli import main

    stack.save(tmp_path / "s")
    assert main(["export", str(tmp_path / "s"), "--normal-map", str(tmp_path / "gl.png")]) == 0
    assert main(["export", str(tmp_path / "s"), "--normal-map", str(tmp_path / "dx.png"), "--directx"]) == 0

    def codes(path):
        w, h, rows, _ = png.Reader(filename=str(path)).read()
        return np.array([list(r) for r in rows], dtype=np.int64).reshape(h, w, 3)

    gl, dx = codes(tmp_path / "gl.png"), codes(tmp_path / "dx.png")
    np.testing.assert_array_equal(dx[..., [0, 2]], gl[..., [0, 2]])
    np.testing.assert_array_equal(dx[..., 1], 65535 - gl[..., 1])
    assert main(["add-surface", str(tmp_path / "s"), str(tmp_path / "dx.png"), "--id", "dx", "--directx"]) == 0
    assert main(["add-surface", str(tmp_path / "s"), str(tmp_path / "gl.png"), "--id", "gl"]) == 0
    back = load_stack(tmp_path / "s")
    np.testing.assert_array_equal(back.tensors["dx"].color.numpy(), back.tensors["gl"].color.numpy())
    assert float((back.tensors["dx"].color - back.tensors["shape"].color).abs().max()) <= 1 / 65535  # float32 normals
    capsys.readouterr()
    assert main(["export", str(tmp_path / "s"), "--directx", "--ora", str(tmp_path / "x.ora")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--directx is the convention --normal-map writes in" in err[0]


def read_grey16(path) -> np.ndarray:
    w, h, rows, info = png.Reader(filename=str(path)).read()
    assert info["bitdepth"] == 16 and info["planes"] == 1
    return np.array([list(r) for r in rows], dtype=np.float64).reshape(h, w) / 65535.0


@pytest.mark.parametrize("max_side", [None, 28])
def test_export_height_map_gives_back_the_heights_the_normals_came_from(tmp_path, capsys, monkeypatch, max_side):
    """``--height-map``: a surface layer made from a known height field (two bumps, in canvas units) exports the
    heights that field had — black its lowest point, white the printed peak in pixels — within 3 % of the peak, read
    back with pypng in float64 (6 % when a canvas over ``HEIGHT_MAX_SIDE`` is integrated at half size and enlarged); a
    flat map is all black with peak 0; --surface picks the layer."""
    from lasagna.cli import main
    from lasagna.export import png as png_export

    if max_side is not None:
        monkeypatch.setattr(png_export, "HEIGHT_MAX_SIDE", max_side)

    h, w = 40, 56
    y, x = np.meshgrid(np.linspace(-h / w, h / w, h), np.linspace(-1, 1, w), indexing="ij")
    bump = 0.25 * np.exp(-(x**2 + y**2) / 0.1) + 0.1 * np.exp(-((x - 0.55) ** 2 + (y + 0.2) ** 2) / 0.03)
    s = Stack.from_image(torch.full((3, h, w), 0.5))
    s.add_surface("shape", normals_from_height(torch.from_numpy(bump)[None, None])[0].float(), "left")
    flat = torch.zeros(3, h, w)
    flat[2] = 1.0
    s.add_surface("flat", flat, "left")
    s.save(tmp_path / "s")
    assert main(["export", str(tmp_path / "s"), "--height-map", str(tmp_path / "h.png"), "--surface", "shape"]) == 0
    out = capsys.readouterr().out
    peak = float(out.split("white ")[1].split(" pixels")[0])
    want = (bump - bump.min()) * (w / 2)  # canvas units (2 across) to pixels
    tol = 0.03 if max_side is None else 0.06  # reduced to half its width, the narrow bump's slopes are averaged
    assert abs(peak - want.max()) < tol * want.max()
    np.testing.assert_allclose(read_grey16(tmp_path / "h.png") * peak, want, atol=tol * want.max())
    assert main(["export", str(tmp_path / "s"), "--height-map", str(tmp_path / "f.png")]) == 0  # the topmost: flat
    assert "white 0 pixels" in capsys.readouterr().out and not read_grey16(tmp_path / "f.png").any()


def test_export_occlusion_map_is_the_share_of_the_sky_its_heights_see(tmp_path, capsys):
    """``--occlusion-map``: a surface layer made from a plateau exports, 16-bit grey read back with pypng in float64,
    the share of a cosine-weighted sky each point sees over the heights the normals came from (a numpy float64 mean
    of ray marches, tests/support/lights.py) — within 0.04 in the mean, off the border — darker at the plateau's foot,
    white on open ground; a flat layer's map is all white."""
    from lasagna.cli import main
    from tests.support.lights import sky_share

    height = 3 * plateau()
    s = Stack.from_image(torch.full((3, 48, 64), 0.5))
    s.add_surface("shape", normals_from_height(height.float())[0], "left")
    flat = torch.zeros(3, 48, 64)
    flat[2] = 1.0
    s.add_surface("flat", flat, "left")
    s.save(tmp_path / "s")
    assert main(["export", str(tmp_path / "s"), "--occlusion-map", str(tmp_path / "ao.png"), "--surface", "shape"]) == 0
    assert "wrote" in capsys.readouterr().out
    got = read_grey16(tmp_path / "ao.png")
    want = sky_share(height[0, 0].numpy() - float(height.min()))
    assert np.abs(got - want)[3:-3, 3:-3].mean() <= 0.04 and want.min() < 0.7
    assert got[22, 36] < 0.8 and got[5, 58] > 0.95 and abs(got[5, 58] - want[5, 58]) < 0.05  # its foot; open ground
    assert main(["export", str(tmp_path / "s"), "--occlusion-map", str(tmp_path / "f.png")]) == 0  # the topmost: flat
    assert (read_grey16(tmp_path / "f.png") == 1.0).all()


def test_export_height_map_refusals_are_one_line_and_write_nothing(stack, tmp_path, capsys):
    """No surface layer, --surface without a map to write, or the height map aimed at the stack's own normal map: one
    line, exit 2, nothing written or changed."""
    from lasagna.cli import main

    stack.save(tmp_path / "own")
    own = tmp_path / "own" / "layers" / "shape.png"
    before = own.read_bytes()
    assert main(["export", str(tmp_path / "own"), "--height-map", str(own)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not one of the stack's files" in err and own.read_bytes() == before

    Stack.from_image(torch.rand(3, 8, 8)).save(tmp_path / "s")
    assert main(["export", str(tmp_path / "s"), "--height-map", str(tmp_path / "h.png")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no surface layer" in err and not (tmp_path / "h.png").exists()
    assert main(["export", str(tmp_path / "s"), "--occlusion-map", str(tmp_path / "ao.png")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no surface layer" in err and not (tmp_path / "ao.png").exists()
    assert main(["export", str(tmp_path / "s"), "--surface", "base", "--layers", str(tmp_path / "l")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "expected one of them too" in err and not (tmp_path / "l").exists()


def test_a_2d_engine_lights_our_map_as_we_do(stack, tmp_path):
    """Round trip through the convention a 2D engine reads (Godot's CanvasTexture normal map, OpenGL +Y up):
    decode n = 2·rgb − 1 from the exported 8-bit-per-channel-or-better PNG, light with N·L as a Light2D does
    (its height gives the light's z), and the engine's Lambert term equals our shading's."""
    from lasagna.cli import main

    stack.save(tmp_path / "s")
    main(["export", str(tmp_path / "s"), "--normal-map", str(tmp_path / "n.png")])
    rgb = np.asarray(
        [list(r) for r in png.Reader(filename=str(tmp_path / "n.png")).read()[2]], dtype=np.float64
    ).reshape(12, 16, 3)
    engine_n = rgb / 65535.0 * 2 - 1  # Godot: NORMAL_MAP texture.rgb * 2.0 - 1.0, green up
    engine_n /= np.linalg.norm(engine_n, axis=-1, keepdims=True)
    # A light up and to the right of the screen: screen y runs down in the engine, so "up" is +Y of the map.
    l_vec = light(45, 50)
    engine = np.maximum(0, engine_n @ l_vec)
    stack.set_light("shape", "az=45,el=50")
    ours = (stack.render().image.double().numpy() / stack.tensors["base"].color.double().numpy().clip(1e-6))[0]
    ours_lambert = (ours - 0.25) / 0.75
    visible = stack.tensors["base"].color.double().numpy()[0] > 0.05  # where the ratio is well defined
    np.testing.assert_allclose(ours_lambert[visible], engine[visible], atol=1e-4)


def test_ora_and_psd_carry_the_normal_map_hidden_below_the_shading(stack, tmp_path):
    from lasagna.export import import_ora
    from lasagna.export.ora_import import read_ora

    stack.save(tmp_path / "s")
    from lasagna.cli import main

    assert (
        main(["export", str(tmp_path / "s"), "--ora", str(tmp_path / "s.ora"), "--psd", str(tmp_path / "s.psd")]) == 0
    )
    _, _, layers = read_ora(tmp_path / "s.ora")  # the file's own layers (an import makes the pair one surface again)
    names = [layer["name"] for layer in layers]
    hidden = [layer for layer in layers if layer["name"].endswith("(normal map)")]
    assert len(hidden) == 1 and not hidden[0]["visible"] and names.index(hidden[0]["name"]) < len(names) - 1
    stored = stack.tensors["shape"].color.double().numpy()
    np.testing.assert_allclose(hidden[0]["image"].color, stored, atol=0.5 / 255 + 1e-9)
    back = import_ora(tmp_path / "s.ora")
    assert back.document.layer("shape").kind == "surface" and len(back.document.layers) == len(names) - 2
    from psd_tools import PSDImage

    psd = PSDImage.open(tmp_path / "s.psd")
    psd_names = {layer.name: layer.visible for layer in psd.descendants()}
    assert psd_names.get("shape (normal map)") is False


# ---- the relief gain ------------------------------------------------------------------------------


def deepened(n: np.ndarray, g: float) -> np.ndarray:
    """float64 closed form of a relief gain g: (g·n_x, g·n_y, n_z) renormalised (the normals of g·h)."""
    v = np.concatenate([g * n[:2], n[2:]])
    return v / np.linalg.norm(v, axis=0, keepdims=True)


def test_the_relief_gain_lights_the_maps_slopes_times_g_and_reads_back(stack, tmp_path):
    """``relief`` g renders Lambert of the stored map's normals with their slopes times g (numpy float64 from the
    PNG read by pypng), shading and relight alike; relief 1 is the map as stored, bit for bit; the gain is saved
    in stack.json and the stack re-renders the same bits; editing it in stack.json re-renders exactly."""
    stack.save(tmp_path / "s")
    n = read_normals(tmp_path / "s" / "layers" / "shape.png")
    base = stack.tensors["base"].color.double().numpy()
    at_one = stack.render().image
    stack.set_light("shape", "left", relief=1.0)
    assert torch.equal(stack.render().image, at_one)
    for g in (0.5, 2.0, 5.0):
        stack.set_light("shape", "az=200,el=40", relief=g)
        ref = np.clip(base * shading(deepened(n, g), light(200, 40))[None], 0, 1)
        np.testing.assert_allclose(stack.render().image.double().numpy(), ref, atol=2e-6)
    stack.set_light("shape", "right", source_light="left", relief=3.0)
    m = deepened(n, 3.0)
    ratio = shading(m, light(0, 60)) / shading(m, light(180, 60))
    np.testing.assert_allclose(stack.render().image.double().numpy(), np.clip(base * ratio, 0, 1), atol=2e-6)
    stack.save(tmp_path / "t")
    doc = json.loads((tmp_path / "t" / "stack.json").read_text())
    assert doc["layers"][1]["relief"] == 3.0
    assert torch.equal(load_stack(tmp_path / "t").render().image, stack.render().image)
    doc["layers"][1]["relief"] = 1.5
    (tmp_path / "t" / "stack.json").write_text(json.dumps(doc))
    stack.set_light("shape", "right", relief=1.5)
    assert torch.equal(load_stack(tmp_path / "t").render().image, stack.render().image)


@pytest.mark.parametrize(
    "field, value",
    [
        *(("relief", v) for v in (0, -1, 16.5, "2")),
        *(("light_color", v) for v in ([1, 1], [1, 1, 1.5], [-0.1, 1, 1], "white")),
        *(("gloss", v) for v in (-0.1, 1.5, "0.5")),
        *(("shininess", v) for v in (0.5, 2000)),
        *(("shadows", v) for v in (-0.1, 1.5, "0.5", True)),
        *(("occlusion", v) for v in (-0.1, 1.5, "0.5", None)),
        *(("shadow_depth", v) for v in (0, -1, 16.5, "2")),
    ],
)
def test_a_bad_relief_or_light_colour_is_refused_by_the_model_and_the_schema(field, value):
    doc = json.loads(json.dumps(VALID))
    doc["layers"][1][field] = value
    with pytest.raises(DocumentError, match=rf"layers\[1\]\.{field}"):
        Document.from_dict(doc)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(doc, ROOT_SCHEMA)


def test_a_relieved_layer_exports_the_map_it_lights(stack, tmp_path):
    """With relief g ≠ 1 the exported normal map (`--normal-map`, and the hidden layer of ORA) is the stored map's
    normals deepened by g, so a reader lights it as the layer renders; the ORA still flattens to the composite."""
    from lasagna.cli import main
    from lasagna.export import import_ora
    from lasagna.export.ora_import import read_ora

    stack.save(tmp_path / "plain")
    stored = read_normals(tmp_path / "plain" / "layers" / "shape.png")
    stack.set_light("shape", "az=120,el=55", relief=2.5)
    stack.save(tmp_path / "s")
    assert main(["export", str(tmp_path / "s"), "--normal-map", str(tmp_path / "n.png")]) == 0
    assert main(["export", str(tmp_path / "s"), "--ora", str(tmp_path / "s.ora")]) == 0
    np.testing.assert_allclose(read_normals(tmp_path / "n.png"), deepened(stored, 2.5), atol=1e-4)
    _, _, layers = read_ora(tmp_path / "s.ora")
    hidden = next(layer for layer in layers if layer["name"].endswith("(normal map)"))
    codes = hidden["image"].color
    np.testing.assert_allclose(codes, (deepened(stored, 2.5) + 1) / 2, atol=0.5 / 255 + 1e-4)
    back = import_ora(tmp_path / "s.ora")  # read back as a surface of the deepened map, relief 1
    assert back.document.layer("shape").kind == "surface" and back.document.layer("shape").relief == 1.0
    np.testing.assert_allclose(
        back.render().image.double().numpy(), stack.render().image.double().numpy(), atol=1.5 / 255
    )


# ---- the light's colour ---------------------------------------------------------------------------


def test_a_coloured_light_colours_the_direct_term_per_channel(stack, tmp_path):
    """``light_color`` c renders a + (1 − a)·c_k·max(0, n·l) per channel k (numpy float64 of the map read by pypng),
    the source light of a relight staying white; white is the one-channel multiplier bit for bit; saved and read
    back it renders the same bits; the ORA of the coloured shading flattens to it."""

    stack.save(tmp_path / "s")
    n = read_normals(tmp_path / "s" / "layers" / "shape.png")
    base = stack.tensors["base"].color.double().numpy()
    white = stack.render().image
    stack.set_light("shape", "left", light_color=(1.0, 1.0, 1.0))
    assert torch.equal(stack.render().image, white)
    c = np.array([1.0, 0.7, 0.4])
    stack.set_light("shape", "az=60,el=50", light_color=tuple(c))
    direct = np.maximum(0.0, np.einsum("chw,c->hw", n, light(60, 50)))
    ref = np.clip(base * (0.25 + 0.75 * c[:, None, None] * direct[None]), 0, 1)
    np.testing.assert_allclose(stack.render().image.double().numpy(), ref, atol=2e-6)
    stack.set_light("shape", "right", source_light="left", light_color=tuple(c))
    lit = 0.25 + 0.75 * c[:, None, None] * np.maximum(0.0, np.einsum("chw,c->hw", n, light(0, 60)))[None]
    ratio = lit / shading(n, light(180, 60))[None]
    np.testing.assert_allclose(stack.render().image.double().numpy(), np.clip(base * ratio, 0, 1), atol=2e-6)
    stack.save(tmp_path / "t")
    assert json.loads((tmp_path / "t" / "stack.json").read_text())["layers"][1]["light_color"] == list(c)
    assert torch.equal(load_stack(tmp_path / "t").render().image, stack.render().image)

    stack.set_light("shape", "az=60,el=50", source_light=None)  # coloured shading: every value ≤ 1, exact in ORA
    assert_files_flatten(stack, tmp_path / "u")  # psd-tools flattens the three-channel multiply layer as we do


# ---- a point light ---------------------------------------------------------------------------------


def point_shading(n: np.ndarray, x: float, y: float, z: float, a: float = 0.25) -> np.ndarray:
    """numpy float64 of a point light over a (3, h, w) map: pixel (i, j) at ((j + ½)/w, (i + ½)/h), the vector to
    the light in units of the longer side with y up, inverse-square falloff (z/|d|)² (1 beneath the light)."""
    _, h, w = n.shape
    side = max(h, w)
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    d = np.stack([(x - (jj + 0.5) / w) * w / side, ((ii + 0.5) / h - y) * h / side, np.full((h, w), z)])
    dist = np.linalg.norm(d, axis=0)
    return a + (1 - a) * (z / dist) ** 2 * np.maximum(0.0, (n * d / dist).sum(0))


def test_a_point_light_lights_each_pixel_from_where_it_stands(stack, tmp_path):
    """``light`` 'x=…,y=…,z=…' renders the module's closed form against numpy float64 of the map read by pypng,
    for shading, a coloured light and a relight ratio; a flat map under it is brightest beneath the light and falls
    off by (z/|d|)³; stack.json round-trips it bit for bit; the ORA and the PSD flatten to it."""

    stack.save(tmp_path / "s")
    n = read_normals(tmp_path / "s" / "layers" / "shape.png")
    base = stack.tensors["base"].color.double().numpy()
    for x, y, z in ((0.25, 0.5, 0.3), (-1.0, 2.0, 0.05), (0.9, 0.1, 3.0)):
        stack.set_light("shape", f"x={x},y={y},z={z}")
        ref = np.clip(base * point_shading(n, x, y, z)[None], 0, 1)
        np.testing.assert_allclose(stack.render().image.double().numpy(), ref, atol=2e-6)
    c = np.array([1.0, 0.6, 0.3])
    stack.set_light("shape", "x=0.2,y=0.3,z=0.4", light_color=tuple(c), source_light="left")
    lit = 0.25 + c[:, None, None] * (point_shading(n, 0.2, 0.3, 0.4) - 0.25)[None]
    ratio = lit / shading(n, light(180, 60))[None]
    np.testing.assert_allclose(stack.render().image.double().numpy(), np.clip(base * ratio, 0, 1), atol=2e-6)
    stack.save(tmp_path / "t")
    doc = json.loads((tmp_path / "t" / "stack.json").read_text())
    assert doc["layers"][1]["light"] == "x=0.2,y=0.3,z=0.4"
    jsonschema.validate(doc, ROOT_SCHEMA)
    assert torch.equal(load_stack(tmp_path / "t").render().image, stack.render().image)
    stack.set_light("shape", "x=0.7,y=0.6,z=0.5", source_light=None, light_color=(1.0, 1.0, 1.0))
    assert_files_flatten(stack, tmp_path / "u")


def test_a_point_light_over_a_flat_map_falls_off_as_a_point_source():
    """A flat map (n = +z) under a point light at height z: S − a = (1 − a)·(z/r)³, r the distance to the light —
    the irradiance of a point source on a plane (cos θ / r², normalised beneath it); the row through the light is
    symmetric about it."""
    s = Stack.from_image(torch.ones(3, 9, 15))
    s.add_surface("flat", torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, 9, 15).clone(), "top")
    s.set_light("flat", "x=0.5,y=0.5,z=0.2")
    got = s.render().image[0].double().numpy()
    jj, ii = np.meshgrid(np.arange(15), np.arange(9))
    r = np.sqrt(((jj + 0.5) / 15 - 0.5) ** 2 + (((ii + 0.5) / 9 - 0.5) * 9 / 15) ** 2 + 0.04)
    # The stored 16-bit map holds +z to 1.5e-5 per component, so S is within 3e-5 (compose.surface's bound).
    np.testing.assert_allclose(got, 0.25 + 0.75 * (0.2 / r) ** 3, atol=3e-5)
    assert got[4, 7] == got.max() and np.allclose(got[4], got[4, ::-1], atol=3e-5)


@pytest.mark.parametrize(
    "text",
    [
        "x=0.5,y=0.5",
        "x=0.5,y=0.5,z=0",
        "x=0.5,y=0.5,z=-1",
        "x=0.5,x=0.5,z=1",
        "x=nan,y=0,z=1",
        "x=40,y=0,z=1",
        "x=0,y=0,z=100",
        "x=0.5,y=0.5,z=1e-300",  # beneath it, z² would underflow: 0/0
        "x=0,y=0,z=1,az=3",
        "x=0,y=0,z=1,ax=0.5,ay=0.5",  # an aim without a cone
        "x=0,y=0,z=1,cone=0",
        "x=0,y=0,z=1,cone=91",
        "x=0,y=0,z=1,cone=30,ax=0.5",
        "x=0,y=0,z=1,cone=30,blend=1.5",
        "x=0,y=0,z=1,cone=30,ax=40,ay=0",
        "x=0,y=0,z=1,cone=30,cone=40",
    ],
)
def test_a_bad_point_light_is_refused_by_the_model(text):
    doc = json.loads(json.dumps(VALID))
    doc["layers"][1]["light"] = text
    with pytest.raises(DocumentError, match=r"layers\[1\]\.light: .*point light 'x=X,y=Y,z=Z'"):
        Document.from_dict(doc)


def test_a_spot_light_renders_round_trips_and_flattens(stack, tmp_path):
    """``light`` with a cone renders numpy float64 of the spot's closed form (tests/compose/test_surface.py) from
    the map read by pypng; stack.json keeps the text and the schema accepts it; the ORA and the PSD flatten to it."""
    from tests.support.lights import spot_reference

    stack.save(tmp_path / "s")
    n = read_normals(tmp_path / "s" / "layers" / "shape.png")
    base = stack.tensors["base"].color.double().numpy()
    text = "x=0.2,y=0.3,z=0.4,cone=25,ax=0.6,ay=0.7,blend=0.3"
    stack.set_light("shape", text)
    ref = np.clip(base * spot_reference(n, 0.2, 0.3, 0.4, 25.0, 0.6, 0.7, 0.3)[None], 0, 1)
    np.testing.assert_allclose(stack.render().image.double().numpy(), ref, atol=2e-6)
    stack.save(tmp_path / "t")
    doc = json.loads((tmp_path / "t" / "stack.json").read_text())
    assert doc["layers"][1]["light"] == text
    jsonschema.validate(doc, ROOT_SCHEMA)
    assert torch.equal(load_stack(tmp_path / "t").render().image, stack.render().image)
    assert_files_flatten(stack, tmp_path / "u")


def test_a_point_light_is_a_surface_layers_only():
    doc = json.loads(json.dumps(VALID))
    doc["layers"][1]["source_light"] = "x=0.5,y=0.5,z=1"  # a relight's source is a direction, fitted or given
    with pytest.raises(DocumentError, match=r"layers\[1\]\.source_light"):
        Document.from_dict(doc)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(doc, ROOT_SCHEMA)


# ---- the light's intensity -----------------------------------------------------------------------


def test_the_intensity_scales_the_direct_term_and_the_files_flatten_to_it(stack, tmp_path):
    """``light_intensity`` k renders a + (1 − a)·k·c·max(0, n·l) (numpy float64 of the map read by pypng): 1 is the
    layer as before bit for bit; above 1 the shading brightens (values above 1); a relight ratio scales its
    target's direct term; stack.json round-trips it; the ORA (and the PSD, through its exact composite where a
    multiplier exceeds 1) flatten to the composite."""

    stack.save(tmp_path / "s")
    n = read_normals(tmp_path / "s" / "layers" / "shape.png")
    base = stack.tensors["base"].color.double().numpy()
    plain = stack.render().image
    stack.set_light("shape", "left", light_intensity=1.0)
    assert torch.equal(stack.render().image, plain)
    stack.set_light("shape", "az=60,el=50", light_intensity=1.8)
    s = 0.25 + 0.75 * 1.8 * np.maximum(0.0, np.einsum("chw,c->hw", n, light(60, 50)))
    assert s.max() > 1.2
    np.testing.assert_allclose(stack.render().image.double().numpy(), np.clip(base * s[None], 0, 1), atol=2e-6)
    stack.set_light("shape", "right", source_light="left", light_intensity=0.5)
    ratio = (0.25 + 0.75 * 0.5 * np.maximum(0.0, np.einsum("chw,c->hw", n, light(0, 60)))) / shading(n, light(180, 60))
    np.testing.assert_allclose(stack.render().image.double().numpy(), np.clip(base * ratio, 0, 1), atol=2e-6)
    stack.set_light("shape", "az=60,el=50", source_light=None, light_intensity=1.8)
    stack.save(tmp_path / "t")
    assert json.loads((tmp_path / "t" / "stack.json").read_text())["layers"][1]["light_intensity"] == 1.8
    ours = stack.render().image
    assert torch.equal(load_stack(tmp_path / "t").render().image, ours)
    assert_files_flatten(stack, tmp_path / "t")


@pytest.mark.parametrize("value", [0, -1, 8.5, "2", float("nan")])
def test_a_bad_intensity_is_refused_by_the_model_and_the_schema(value):
    doc = json.loads(json.dumps(VALID))
    doc["layers"][1]["light_intensity"] = value
    with pytest.raises(DocumentError, match=r"layers\[1\]\.light_intensity"):
        Document.from_dict(doc)
    if value == value:  # NaN is not JSON: the schema never sees one
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(doc, ROOT_SCHEMA)


# ---- several lights --------------------------------------------------------------------------------


def test_extra_lights_add_their_direct_terms(stack, tmp_path):
    """``extra_lights`` add each light's direct term to the layer's own: a + (1 − a)·Σ kᵢ·cᵢ·fᵢ·max(0, n·lᵢ) (numpy
    float64 of the map read by pypng: a direction, a coloured point light, a relight ratio over its source); none is
    the layer as before bit for bit; stack.json round-trips them; the ORA and the PSD flatten to the composite."""

    stack.save(tmp_path / "s")
    n = read_normals(tmp_path / "s" / "layers" / "shape.png")
    base = stack.tensors["base"].color.double().numpy()
    plain = stack.render().image
    stack.set_light("shape", "left", extra_lights=())
    assert torch.equal(stack.render().image, plain)
    fill = {"light": "x=0.9,y=0.2,z=0.5", "color": (0.6, 0.7, 1.0), "intensity": 0.8}
    stack.set_light("shape", "left", extra_lights=[{"light": "az=10,el=70", "intensity": 0.5}, fill])
    key = np.maximum(0.0, np.einsum("chw,c->hw", n, light(180, 60)))
    second = 0.5 * np.maximum(0.0, np.einsum("chw,c->hw", n, light(10, 70)))
    third = 0.8 * np.array(fill["color"])[:, None, None] * ((point_shading(n, 0.9, 0.2, 0.5) - 0.25) / 0.75)[None]
    s = 0.25 + 0.75 * (key + second)[None] + 0.75 * third
    np.testing.assert_allclose(stack.render().image.double().numpy(), np.clip(base * s, 0, 1), atol=2e-6)
    stack.set_light("shape", "right", source_light="top")
    key = np.maximum(0.0, np.einsum("chw,c->hw", n, light(0, 60)))
    ratio = (0.25 + 0.75 * (key + second)[None] + 0.75 * third) / shading(n, light(90, 60))[None]
    np.testing.assert_allclose(stack.render().image.double().numpy(), np.clip(base * ratio, 0, 1), atol=2e-6)
    stack.set_light("shape", "right", source_light=None)
    stack.save(tmp_path / "t")
    doc = json.loads((tmp_path / "t" / "stack.json").read_text())
    assert [e["light"] for e in doc["layers"][1]["extra_lights"]] == ["az=10,el=70", "x=0.9,y=0.2,z=0.5"]
    jsonschema.validate(doc, ROOT_SCHEMA)
    ours = stack.render().image
    assert torch.equal(load_stack(tmp_path / "t").render().image, ours)
    assert_files_flatten(stack, tmp_path / "t")


@pytest.mark.parametrize(
    "extra, where",
    [
        ([{"light": "up"}], r"extra_lights\[0\]\.light"),
        ([{"light": "left", "intensity": 0}], r"extra_lights\[0\]\.intensity"),
        ([{"light": "left", "color": [1, 2, 0]}], r"extra_lights\[0\]\.color"),
        ([{"light": "left", "gloss": 1}], r"extra_lights\[0\]\.gloss"),
        ([{"light": "left"}] * 9, r"extra_lights"),
        ("left", r"extra_lights"),
    ],
)
def test_bad_extra_lights_are_refused_by_the_model_and_the_schema(extra, where):
    doc = json.loads(json.dumps(VALID))
    doc["layers"][1]["extra_lights"] = extra
    with pytest.raises(DocumentError, match=rf"layers\[1\]\.{where}"):
        Document.from_dict(doc)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(doc, ROOT_SCHEMA)


# ---- gloss: a Blinn–Phong highlight ----------------------------------------------------------------------


def test_gloss_adds_a_blinn_phong_highlight_and_the_files_flatten_to_it(stack, tmp_path):
    """``gloss`` g and ``shininess`` p render a + (1 − a)·k·(max(0, n·l) + g·max(0, n·h)^p·[n·l > 0]) (numpy float64 of
    the map read by pypng, Blinn 1977): gloss 0 is the layer as before bit for bit; a relight ratio keeps its source
    light diffuse; a point light's highlight carries its falloff; stack.json round-trips it; the ORA and the PSD
    flatten to it."""
    from tests.support.lights import blinn_phong

    stack.save(tmp_path / "s")
    n = read_normals(tmp_path / "s" / "layers" / "shape.png")
    base = stack.tensors["base"].color.double().numpy()
    plain = stack.render().image
    stack.set_light("shape", "left", gloss=0.0, shininess=8.0)
    assert torch.equal(stack.render().image, plain)
    l_vec = light(60, 40)
    stack.set_light("shape", "az=60,el=40", gloss=0.6, shininess=8.0, light_intensity=1.5)
    s = 0.25 + 0.75 * 1.5 * (np.maximum(0.0, np.einsum("chw,c->hw", n, l_vec)) + 0.6 * blinn_phong(n, l_vec, 8.0))
    assert (s - shading(n, l_vec)).max() > 0.3  # the highlight shows
    np.testing.assert_allclose(stack.render().image.double().numpy(), np.clip(base * s[None], 0, 1), atol=2e-6)
    stack.set_light("shape", "right", source_light="left", gloss=0.6, shininess=8.0, light_intensity=1.0)
    target = 0.25 + 0.75 * (
        np.maximum(0.0, np.einsum("chw,c->hw", n, light(0, 60))) + 0.6 * blinn_phong(n, light(0, 60), 8)
    )
    ratio = target / shading(n, light(180, 60))
    np.testing.assert_allclose(stack.render().image.double().numpy(), np.clip(base * ratio, 0, 1), atol=2e-6)
    stack.set_light("shape", "x=0.3,y=0.4,z=0.5", source_light=None, gloss=0.5, shininess=16.0)
    _, h, w = n.shape
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    side = max(h, w)
    d = np.stack([(0.3 - (jj + 0.5) / w) * w / side, ((ii + 0.5) / h - 0.4) * h / side, np.full((h, w), 0.5)])
    dist = np.linalg.norm(d, axis=0)
    spec = 0.75 * 0.5 * (0.5 / dist) ** 2 * blinn_phong(n, d / dist, 16.0)
    np.testing.assert_allclose(
        stack.render().image.double().numpy(), np.clip(base * (point_shading(n, 0.3, 0.4, 0.5) + spec), 0, 1), atol=2e-6
    )
    stack.save(tmp_path / "t")
    saved = json.loads((tmp_path / "t" / "stack.json").read_text())["layers"][1]
    assert saved["gloss"] == 0.5 and saved["shininess"] == 16.0
    jsonschema.validate(json.loads((tmp_path / "t" / "stack.json").read_text()), ROOT_SCHEMA)
    assert torch.equal(load_stack(tmp_path / "t").render().image, stack.render().image)
    stack.set_light("shape", "az=60,el=40", gloss=0.6, shininess=8.0)
    assert_files_flatten(stack, tmp_path / "u")


# ---- shadows: cast over the map's own heights ---------------------------------------------------------------------


def plateau(h: int = 48, w: int = 64) -> torch.Tensor:
    """Heights (1, 1, h, w), canvas units: a smooth-edged plateau 0.25 tall (a box with rounded sides), so the
    normals integrate back to it."""
    rows, cols = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    inside = torch.sigmoid((9 - (cols - 24).abs()) / 1.2) * torch.sigmoid((8 - (rows - 22).abs()) / 1.2)
    return (0.25 * inside)[None, None]


def test_shadows_darken_what_the_maps_own_heights_hide_from_the_light(tmp_path):
    """``shadows`` s renders a + (1 − a)·(1 − s·(1 − V))·max(0, n·l): V a numpy float64 ray march over the heights the
    normals came from (tests/support/lights.py), compared off the shadow's edge (within 2 pixels the integrated heights
    and the traced edge may differ); shadows 0 is the layer as before, bit for bit; a relight ratio's source light
    casts none; stack.json round-trips it; the ORA and the PSD flatten to it."""
    from tests.support.lights import directional_shadow

    height = plateau()
    base = torch.full((3, 48, 64), 200, dtype=torch.uint8)
    stack = Stack.from_image(base)
    stack.add_surface("shape", normals_from_height(height.float())[0], "left")
    stack.save(tmp_path / "s")
    n = read_normals(tmp_path / "s" / "layers" / "shape.png")
    b = stack.tensors["base"].color.double().numpy()
    plain = stack.render().image
    stack.set_light("shape", "left", shadows=0.0)
    assert torch.equal(stack.render().image, plain)
    l_vec = light(180, 65)
    v = directional_shadow(height[0, 0].numpy() - float(height.min()), l_vec)
    far = ~np.any([np.roll(np.roll(v < 0.5, i, 0), j, 1) != (v < 0.5) for i in range(-2, 3) for j in range(-2, 3)], 0)
    assert (v[far] < 0.5).sum() > 60  # a shadow falls to the plateau's right, away from its edge
    stack.set_light("shape", "az=180,el=65", shadows=0.8)
    s = 0.25 + 0.75 * (1 - 0.8 * (1 - v)) * np.maximum(0.0, np.einsum("chw,c->hw", n, l_vec))
    got = stack.render().image.double().numpy()
    np.testing.assert_allclose(got[:, far], np.clip(b * s[None], 0, 1)[:, far], atol=2e-3)
    hidden = far & (v < 0.5) & (np.einsum("chw,c->hw", n, l_vec) > 0.3)  # shadowed where the light would fall
    assert hidden.sum() > 30 and (got[:, hidden] < b[:, hidden] * shading(n, l_vec)[hidden] - 0.1).all()
    stack.set_light("shape", "az=180,el=65", source_light="az=0,el=30", shadows=0.8)
    ratio = s / shading(n, light(0, 30))  # the source light unshadowed
    got = stack.render().image.double().numpy()
    np.testing.assert_allclose(got[:, far], np.clip(b * ratio[None], 0, 1)[:, far], atol=3e-3)
    stack.save(tmp_path / "t")
    saved = json.loads((tmp_path / "t" / "stack.json").read_text())["layers"][1]
    assert saved["shadows"] == 0.8
    jsonschema.validate(json.loads((tmp_path / "t" / "stack.json").read_text()), ROOT_SCHEMA)
    assert torch.equal(load_stack(tmp_path / "t").render().image, stack.render().image)
    stack.set_light("shape", "az=180,el=65", source_light=None, shadows=0.8, gloss=0.3)
    assert_files_flatten(stack, tmp_path / "u")


def test_shadow_depth_lengthens_the_shadows_and_leaves_the_shading(tmp_path):
    """``shadow_depth`` d traces the heights times d: the plateau's shadow is about d times as long (at least 1.8×
    at d 2; its soft rim makes it more than a box's 2×), the shading elsewhere unchanged, d 1 is the layer as before
    bit for bit, and stack.json round-trips it."""
    s = Stack.from_image(torch.full((3, 48, 64), 200, dtype=torch.uint8))
    s.add_surface("shape", normals_from_height(plateau().float())[0], "az=180,el=60")
    plain = s.render().image

    def shadowed(depth: float) -> torch.Tensor:
        s.set_light("shape", "az=180,el=60", shadows=1.0, shadow_depth=depth)
        return s.render().image

    one, two = shadowed(1.0), shadowed(2.0)
    s.set_light("shape", "az=180,el=60", shadows=1.0)  # the depth as set: 2
    assert torch.equal(s.render().image, two)
    length = [int(((plain - img) > 0.05).any(0)[22, 33:].sum()) for img in (one, two)]
    assert length[0] >= 5 and length[1] >= 1.8 * length[0], length  # the plateau's rim is soft: not exactly 2×
    untouched = ((plain - one).abs().amax(0) < 1e-6) & ((plain - two).abs().amax(0) < 1e-6)
    assert untouched.float().mean() > 0.8  # elsewhere the shading is the layer's own
    s.set_light("shape", "az=180,el=60", shadows=1.0, shadow_depth=1.0)
    assert torch.equal(s.render().image, one)
    s.set_light("shape", "az=180,el=60", shadow_depth=2.0)
    s.save(tmp_path / "s")
    assert json.loads((tmp_path / "s" / "stack.json").read_text())["layers"][1]["shadow_depth"] == 2.0
    assert torch.equal(load_stack(tmp_path / "s").render().image, two)


def test_shadows_are_as_long_at_any_size_and_traced_small_on_a_large_layer(monkeypatch):
    """A shadow is in canvas units: the plateau's at twice the size is twice as many pixels long (within 2 of 2×);
    above ``SHADOW_MAX_SIDE`` the heights are traced reduced and the shadow keeps its length."""
    import lasagna.compose.surface as cs

    def shadow_length(size_scale: int) -> int:
        h = torch.nn.functional.interpolate(plateau(), scale_factor=size_scale, mode="bilinear")
        s = Stack.from_image(torch.full((3, 48 * size_scale, 64 * size_scale), 200, dtype=torch.uint8))
        s.add_surface("shape", normals_from_height(h.float())[0], "az=180,el=65")
        plain = s.render().image
        s.set_light("shape", "az=180,el=65", shadows=1.0)
        darker = (s.render().image < plain - 0.05).any(0)
        return int(darker[22 * size_scale].sum())

    one, two = shadow_length(1), shadow_length(2)
    assert one > 8 and abs(two - 2 * one) <= 2, (one, two)
    monkeypatch.setattr(cs, "SHADOW_MAX_SIDE", 64)
    assert abs(shadow_length(2) - two) <= 3


def test_a_reduced_layer_traces_at_the_reduction_of_the_full_trace(monkeypatch):
    """Tensors that are the layer's own reduced by r (a zoom level's, ``LayerTensors.reduced_by``) trace their shadows
    at most SHADOW_MAX_SIDE / r on a side: at the full size's trace reduced by r. A layer below that side is traced
    at its own size, reduced or not; the shadow keeps its length in canvas units."""
    import lasagna.compose.surface as cs
    from lasagna.compose.layer import LayerTensors
    from lasagna.compose.surface import shadow_heights

    monkeypatch.setattr(cs, "SHADOW_MAX_SIDE", 64)
    n = normals_from_height(torch.nn.functional.interpolate(plateau(), scale_factor=4, mode="bilinear").float())
    assert shadow_heights(n).shape[-2:] == (48, 64)  # 192×256 traced at 64 on its long side
    half = torch.nn.functional.interpolate(n, scale_factor=0.5, mode="area")
    assert shadow_heights(half, reduced_by=2).shape[-2:] == (24, 32)  # 96×128, a level's: at 64 / 2
    assert shadow_heights(half).shape[-2:] == (48, 64)
    small = normals_from_height(plateau().float())  # 48×64: traced at its own size at level 0 and reduced at level 1
    assert shadow_heights(small).shape[-2:] == (48, 64)
    assert shadow_heights(torch.nn.functional.interpolate(small, scale_factor=0.5), reduced_by=2).shape[-2:] == (24, 32)

    def shadow_length(tensors: LayerTensors, layer) -> int:
        from lasagna.compose.surface import layer_surface_tensors

        lit = layer_surface_tensors(tensors, layer)[0].color[0]
        return int((lit[lit.shape[0] // 2] < lit.max() - 0.1).sum())

    s = Stack.from_image(torch.full((3, 192, 256), 200, dtype=torch.uint8))
    s.add_surface("shape", n[0], "az=180,el=65")
    s.set_light("shape", "az=180,el=65", shadows=1.0)
    layer, full = s.document.layer("shape"), s.tensors["shape"]
    reduced = LayerTensors(
        torch.nn.functional.interpolate(full.color[None], scale_factor=0.5, mode="area")[0], reduced_by=2
    )
    assert abs(2 * shadow_length(reduced, layer) - shadow_length(full, layer)) <= 4


def test_occlusion_takes_ambient_light_from_where_the_maps_heights_hide_the_sky(tmp_path):
    """``occlusion`` o renders a·(1 − o·(1 − A)) + (1 − a)·max(0, n·l): A the share of a cosine-weighted sky over the
    heights the normals came from (a numpy float64 mean of ray marches, tests/support/lights.py), within 0.04 in the
    mean off the plateau's edges; a relight ratio has it above and below; occlusion 0 is the layer as before, bit for
    bit; stack.json round-trips it; the ORA and the PSD flatten to it."""
    from tests.support.lights import sky_share

    height = 3 * plateau()  # tall enough that its foot sees a third less of the sky
    stack = Stack.from_image(torch.full((3, 48, 64), 200, dtype=torch.uint8))
    stack.add_surface("shape", normals_from_height(height.float())[0], "az=90,el=40")
    stack.save(tmp_path / "s")
    n = read_normals(tmp_path / "s" / "layers" / "shape.png")
    b = stack.tensors["base"].color.double().numpy()
    plain = stack.render().image
    stack.set_light("shape", "az=90,el=40", occlusion=0.0)
    assert torch.equal(stack.render().image, plain)
    sky = sky_share(height[0, 0].numpy() - float(height.min()))
    assert sky.min() < 0.7  # the plateau's foot sees less sky
    inner = np.zeros(sky.shape, dtype=bool)
    inner[3:-3, 3:-3] = True
    l_vec = light(90, 40)
    stack.set_light("shape", "az=90,el=40", occlusion=0.9)
    want = 0.25 * (1 - 0.9 * (1 - sky)) + 0.75 * np.maximum(0.0, np.einsum("chw,c->hw", n, l_vec))
    got = stack.render().image.double().numpy()
    assert np.abs(got - np.clip(b * want, 0, 1))[:, inner].mean() <= 0.04 * 0.8
    foot = inner & (sky < 0.75)
    assert foot.sum() > 20 and (got[:, foot] < plain.double().numpy()[:, foot] - 0.02).all()
    stack.set_light("shape", "az=90,el=40", source_light="left", occlusion=0.9)
    ratio = want / (0.25 * (1 - 0.9 * (1 - sky)) + 0.75 * np.maximum(0.0, np.einsum("chw,c->hw", n, light(180, 60))))
    got = stack.render().image.double().numpy()
    assert np.abs(got - np.clip(b * ratio, 0, 1))[:, inner].mean() <= 0.04
    stack.save(tmp_path / "t")
    saved = json.loads((tmp_path / "t" / "stack.json").read_text())["layers"][1]
    assert saved["occlusion"] == 0.9
    jsonschema.validate(json.loads((tmp_path / "t" / "stack.json").read_text()), ROOT_SCHEMA)
    assert torch.equal(load_stack(tmp_path / "t").render().image, stack.render().image)
    stack.set_light("shape", "az=90,el=40", source_light=None, occlusion=0.9, shadows=0.5)
    assert_files_flatten(stack, tmp_path / "u")
