"""``lasagna light``: a surface layer re-lit in place from its stored map — the composite against numpy float64
Lambert of the map read by pypng, the layer PNGs untouched, the folder's stack.ora kept current, and hostile input
(one line, exit 2, nothing changed)."""

from __future__ import annotations

import io
import json
import math
import zipfile

import numpy as np
import png
import pytest
import torch
from PIL import Image

from lasagna.cli import main
from lasagna.compose.surface import normals_from_height
from lasagna.export.ora import encode_ora
from lasagna.io.stack import Stack, load_stack


def light(az: float, el: float) -> np.ndarray:
    a, e = math.radians(az), math.radians(el)
    return np.array([math.sin(e) * math.cos(a), math.sin(e) * math.sin(a), math.cos(e)])


def read_normals(path) -> np.ndarray:
    w, h, rows, _ = png.Reader(filename=str(path)).read()
    v = np.array([list(r) for r in rows], dtype=np.float64).reshape(h, w, 3).transpose(2, 0, 1) / 65535.0
    n = 2 * v - 1
    return n / np.linalg.norm(n, axis=0, keepdims=True)


def shading(n: np.ndarray, l_vec: np.ndarray, a: float = 0.25) -> np.ndarray:
    return a + (1 - a) * np.maximum(0.0, np.einsum("chw,c->hw", n, l_vec))


def codes(path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB")).astype(int)


@pytest.fixture
def folder(tmp_path):
    torch.manual_seed(3)
    base = (torch.rand(3, 12, 16) * 255).to(torch.uint8)
    s = Stack.from_image(base)
    s.add_surface("shape", normals_from_height(0.1 * torch.randn(1, 1, 12, 16))[0], "left")
    out = tmp_path / "s"
    s.save(out)
    (out / "stack.ora").write_bytes(encode_ora(load_stack(out)))  # as `lasagna edit` leaves a folder
    return out


def layer_bytes(folder) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((folder / "layers").iterdir())}


def test_light_relights_in_place_from_the_stored_map(folder, capsys):
    pngs = layer_bytes(folder)
    assert main(["light", str(folder), "--light", "az=30,el=45", "--relief", "2", "--ambient", "0.3"]) == 0
    assert "re-lit shape: light az=30,el=45, ambient 0.3, relief 2" in capsys.readouterr().out
    doc = json.loads((folder / "stack.json").read_text())["layers"][1]
    assert (doc["light"], doc["ambient"], doc["relief"], doc["source_light"]) == ("az=30,el=45", 0.3, 2.0, None)
    assert layer_bytes(folder) == pngs  # no pixels were written: the map is what it was
    # composite.png against float64 numpy: the base times Lambert of the map's normals, slopes ×2.
    n = read_normals(folder / "layers" / "shape.png")
    deep = np.concatenate([2 * n[:2], n[2:]])
    deep /= np.linalg.norm(deep, axis=0, keepdims=True)
    base = codes(folder / "layers" / "base.png").transpose(2, 0, 1) / 255.0
    want = np.clip(base * shading(deep, light(30, 45), 0.3)[None], 0, 1) * 255
    np.testing.assert_allclose(codes(folder / "composite.png").transpose(2, 0, 1), want, atol=0.51)
    # the stack.ora the folder held now flattens to the new composite
    with zipfile.ZipFile(folder / "stack.ora") as z:
        merged = np.asarray(Image.open(io.BytesIO(z.read("mergedimage.png"))).convert("RGB")).astype(int)
    np.testing.assert_array_equal(merged, codes(folder / "composite.png"))


def test_from_makes_a_relight_ratio_and_none_makes_it_shading_again(folder):
    assert main(["light", str(folder), "--light", "right", "--from", "left"]) == 0
    n = read_normals(folder / "layers" / "shape.png")
    base = codes(folder / "layers" / "base.png").transpose(2, 0, 1) / 255.0
    ratio = shading(n, light(0, 60)) / shading(n, light(180, 60))
    np.testing.assert_allclose(
        codes(folder / "composite.png").transpose(2, 0, 1), np.clip(base * ratio[None], 0, 1) * 255, atol=0.51
    )
    assert main(["light", str(folder), "--relief", "1.5"]) == 0  # the light and source light kept
    doc = json.loads((folder / "stack.json").read_text())["layers"][1]
    assert (doc["light"], doc["source_light"], doc["relief"]) == ("right", "left", 1.5)
    assert main(["light", str(folder), "--from", "none"]) == 0
    assert json.loads((folder / "stack.json").read_text())["layers"][1]["source_light"] is None


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            [],
            "light: nothing to change; expected at least one of --light, --from, --ambient, --relief, --color, "
            "--intensity, --gloss, --shininess, --shadows, --shadow-depth, --occlusion, --add-light, --clear-lights",
        ),
        (["--intensity", "0"], "layers[1].light_intensity: got 0.0; expected greater than 0"),
        (["--add-light", "up"], "layers[1].extra_lights[0].light: expected one of left"),
        (["--add-light", "left;red"], "--add-light: got 'red'; expected #rrggbb or R,G,B"),
        (["--add-light", "left;;x"], "--add-light: got 'left;;x'; its intensity is not a number"),
        (["--add-light", "left;;0"], "layers[1].extra_lights[0].intensity"),
        (
            ["--add-light", "left;#ffffff;1;2"],
            "--add-light: got 'left;#ffffff;1;2'; expected LIGHT[;COLOUR[;INTENSITY]]",
        ),
        (["--add-light", ";#ffffff"], "expected LIGHT[;COLOUR[;INTENSITY]]"),
        (["--add-light", "left"] * 9, "layers[1].extra_lights"),
        (["--intensity", "9"], "layers[1].light_intensity"),
        (["--intensity", "nan"], "layers[1].light_intensity"),
        (["--gloss", "1.5"], "layers[1].gloss: got 1.5; expected less than or equal to 1"),
        (["--gloss", "-0.1"], "layers[1].gloss"),
        (["--shininess", "0.5"], "layers[1].shininess: got 0.5; expected greater than or equal to 1"),
        (["--shininess", "inf"], "layers[1].shininess"),
        (["--shadows", "1.5"], "layers[1].shadows: got 1.5; expected less than or equal to 1"),
        (["--shadows", "nan"], "layers[1].shadows"),
        (["--occlusion", "-0.5"], "layers[1].occlusion: got -0.5; expected greater than or equal to 0"),
        (["--shadow-depth", "0"], "layers[1].shadow_depth: got 0.0; expected greater than 0"),
        (["--color", "red"], "--color: got 'red'; expected #rrggbb or R,G,B"),
        (["--color", "1,0.5"], "--color: got '1,0.5'; expected #rrggbb or R,G,B"),
        (["--color", "1,2,0"], "layers[1].light_color"),
        (["--light", "upward"], "layers[1].light: expected one of left"),
        (["--light", "x=0.5,y=0.5,z=0"], "layers[1].light: expected a point light 'x=X,y=Y,z=Z'"),
        (["--light", "x=0.5,y=0.5"], "layers[1].light: expected a point light 'x=X,y=Y,z=Z'"),
        (["--relief", "0"], "layers[1].relief: got 0.0; expected greater than 0"),
        (["--relief", "17"], "layers[1].relief"),
        (["--ambient", "1"], "layers[1].ambient"),
        (["--from", "left", "--ambient", "0"], "expected ambient > 0"),
        (["--layer", "base", "--light", "left"], "--layer: no surface layer 'base'; expected one of shape"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_changes_nothing(folder, capsys, argv, message):
    before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    assert main(["light", str(folder), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err
    assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} == before


def test_a_stack_without_a_surface_layer_is_refused(tmp_path, capsys):
    Stack.from_image((torch.rand(3, 4, 4) * 255).to(torch.uint8)).save(tmp_path / "plain")
    assert main(["light", str(tmp_path / "plain"), "--light", "left"]) == 2
    assert "the stack has no surface layer; expected one to re-light" in capsys.readouterr().err


def test_color_colours_the_lights_direct_term(folder, capsys):
    assert main(["light", str(folder), "--light", "top", "--color", "#ff8000"]) == 0
    assert "colour 1,0.502,0" in capsys.readouterr().out
    c = np.array([1.0, 128 / 255, 0.0])
    assert json.loads((folder / "stack.json").read_text())["layers"][1]["light_color"] == list(c)
    n = read_normals(folder / "layers" / "shape.png")
    base = codes(folder / "layers" / "base.png").transpose(2, 0, 1) / 255.0
    direct = np.maximum(0.0, np.einsum("chw,c->hw", n, light(90, 60)))
    want = np.clip(base * (0.25 + 0.75 * c[:, None, None] * direct[None]), 0, 1) * 255
    np.testing.assert_allclose(codes(folder / "composite.png").transpose(2, 0, 1), want, atol=0.51)
    assert main(["light", str(folder), "--color", "1,1,1"]) == 0  # white again: the one-channel multiplier
    assert json.loads((folder / "stack.json").read_text())["layers"][1]["light_color"] == [1.0, 1.0, 1.0]


def test_a_point_light_lights_each_pixel_from_where_it_stands(folder, capsys):
    """``--light x=…,y=…,z=…``: the composite against numpy float64 of a point light over the map read by pypng
    (each pixel's own direction to the light, inverse-square falloff, 1 beneath it)."""
    assert main(["light", str(folder), "--light", "x=0.1,y=0.3,z=0.4"]) == 0
    assert "light x=0.1,y=0.3,z=0.4" in capsys.readouterr().out
    n = read_normals(folder / "layers" / "shape.png")
    _, h, w = n.shape
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    d = np.stack([(0.1 - (jj + 0.5) / w) * w / 16, ((ii + 0.5) / h - 0.3) * h / 16, np.full((h, w), 0.4)])
    r = np.linalg.norm(d, axis=0)
    s = 0.25 + 0.75 * (0.4 / r) ** 2 * np.maximum(0.0, (n * d / r).sum(0))
    base = codes(folder / "layers" / "base.png").transpose(2, 0, 1) / 255.0
    want = np.clip(base * s[None], 0, 1) * 255
    np.testing.assert_allclose(codes(folder / "composite.png").transpose(2, 0, 1), want, atol=0.51)


def test_a_spot_light_lights_its_cone(folder, capsys):
    """``--light x=…,cone=…,ax=…,ay=…``: the composite against numpy float64 of the spot's closed form over the map
    read by pypng; a bad cone is one line, exit 2, the stack unchanged."""
    from tests.support.lights import spot_reference

    text = "x=0.1,y=0.3,z=0.4,cone=35,ax=0.6,ay=0.5"
    assert main(["light", str(folder), "--light", text]) == 0
    assert f"light {text}" in capsys.readouterr().out
    n = read_normals(folder / "layers" / "shape.png")
    base = codes(folder / "layers" / "base.png").transpose(2, 0, 1) / 255.0
    want = np.clip(base * spot_reference(n, 0.1, 0.3, 0.4, 35.0, 0.6, 0.5, 0.15)[None], 0, 1) * 255
    np.testing.assert_allclose(codes(folder / "composite.png").transpose(2, 0, 1), want, atol=0.51)
    before = (folder / "stack.json").read_bytes()
    assert main(["light", str(folder), "--light", "x=0.1,y=0.3,z=0.4,cone=120"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "cone=120" in err and "out of range" in err
    assert (folder / "stack.json").read_bytes() == before


def test_an_edit_toward_a_point_light_says_where_a_point_light_goes(tmp_path, capsys):
    """A learned edit's condition is a direction (its prior was trained on directions): a point light there is
    refused in one line, exit 2, saying that a point light is a surface layer's light, set after the edit."""
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tmp_path / "a.png")
    argv = ["edit", str(tmp_path / "a.png"), "--layer", "shading", "--condition", "x=0.1,y=0.5,z=0.4"]
    assert main([*argv, "-o", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert "a point light is only a surface layer's light" in err and err.count("\n") == 1
    assert not (tmp_path / "a").exists()


def test_intensity_scales_the_lights_direct_term(folder, capsys):
    """``--intensity k``: the composite against numpy float64, a + (1 − a)·k·max(0, n·l), brighter than the base where
    the light falls (a shading layer above 1), clamped at 1; with a colour the gain is k·c per channel."""
    assert main(["light", str(folder), "--light", "az=200,el=40", "--intensity", "2.5"]) == 0
    assert "intensity 2.5" in capsys.readouterr().out
    n = read_normals(folder / "layers" / "shape.png")
    base = codes(folder / "layers" / "base.png").transpose(2, 0, 1) / 255.0
    s = 0.25 + 0.75 * 2.5 * np.maximum(0.0, np.einsum("chw,c->hw", n, light(200, 40)))
    assert s.max() > 1.5
    want = np.clip(base * s[None], 0, 1) * 255
    np.testing.assert_allclose(codes(folder / "composite.png").transpose(2, 0, 1), want, atol=0.51)
    assert main(["light", str(folder), "--color", "1,0.5,0.25"]) == 0  # the intensity kept, now coloured
    c = 2.5 * np.array([1.0, 0.5, 0.25])
    direct = np.maximum(0.0, np.einsum("chw,c->hw", n, light(200, 40)))
    want = np.clip(base * (0.25 + 0.75 * c[:, None, None] * direct[None]), 0, 1) * 255
    np.testing.assert_allclose(codes(folder / "composite.png").transpose(2, 0, 1), want, atol=0.51)


def test_gloss_adds_a_highlight_where_the_light_falls(folder, capsys):
    """``--gloss g --shininess p``: the composite against numpy float64, a + (1 − a)·(max(0, n·l) + g·max(0, n·h)^p
    where n·l > 0), h the half vector toward the viewer; the summary says it; --gloss 0 gives the diffuse composite."""
    assert main(["light", str(folder), "--light", "az=200,el=40", "--gloss", "0.8", "--shininess", "6"]) == 0
    assert "gloss 0.8 (shininess 6)" in capsys.readouterr().out
    n = read_normals(folder / "layers" / "shape.png")
    base = codes(folder / "layers" / "base.png").transpose(2, 0, 1) / 255.0
    l_vec = light(200, 40)
    half = (l_vec + np.array([0.0, 0.0, 1.0])) / np.linalg.norm(l_vec + np.array([0.0, 0.0, 1.0]))
    ndotl = np.einsum("chw,c->hw", n, l_vec)
    spec = np.maximum(0.0, np.einsum("chw,c->hw", n, half)) ** 6 * (ndotl > 0)
    s = 0.25 + 0.75 * (np.maximum(0.0, ndotl) + 0.8 * spec)
    want = np.clip(base * s[None], 0, 1) * 255
    np.testing.assert_allclose(codes(folder / "composite.png").transpose(2, 0, 1), want, atol=0.51)
    assert main(["light", str(folder), "--gloss", "0"]) == 0
    diffuse = np.clip(base * (0.25 + 0.75 * np.maximum(0.0, ndotl))[None], 0, 1) * 255
    np.testing.assert_allclose(codes(folder / "composite.png").transpose(2, 0, 1), diffuse, atol=0.51)


def test_shadows_darken_what_the_surfaces_heights_hide_and_zero_removes_them(tmp_path, capsys):
    """``--shadows s`` with a low light: the composite is the stack's own render of that light (the library's
    shadows are tested against a numpy ray march in tests/io/test_surface_layer.py), darker than the shadowless
    composite behind the bump and nowhere brighter; the summary says it; ``--shadows 0`` gives the shadowless
    composite again, code for code; the layer PNGs are untouched."""
    rows, cols = torch.meshgrid(torch.arange(24.0), torch.arange(32.0), indexing="ij")
    bump = 0.3 * torch.exp(-((rows - 12) ** 2 + (cols - 10) ** 2) / 18.0)[None, None]
    s = Stack.from_image(torch.full((3, 24, 32), 180, dtype=torch.uint8))
    s.add_surface("shape", normals_from_height(bump)[0], "az=180,el=70")
    folder = tmp_path / "s"
    s.save(folder)
    assert main(["light", str(folder), "--shadows", "0"]) == 0  # writes the shadowless composite
    plain = codes(folder / "composite.png")
    files = layer_bytes(folder)
    assert main(["light", str(folder), "--shadows", "0.9"]) == 0
    assert "shadows 0.9" in capsys.readouterr().out
    shadowed = codes(folder / "composite.png")
    assert (shadowed <= plain).all() and (shadowed < plain - 20).any(axis=2)[:, 14:].sum() > 10
    assert np.array_equal(shadowed, composite_of(folder)) and layer_bytes(folder) == files
    assert json.loads((folder / "stack.json").read_text())["layers"][1]["shadows"] == 0.9
    assert main(["light", str(folder), "--shadows", "0"]) == 0
    assert np.array_equal(codes(folder / "composite.png"), plain)
    assert main(["light", str(folder), "--occlusion", "1"]) == 0  # the bump's foot sees less of the sky
    assert "occlusion 1" in capsys.readouterr().out
    occluded = codes(folder / "composite.png")
    assert (occluded <= plain).all() and (occluded < plain - 3).any() and np.array_equal(occluded, composite_of(folder))
    assert main(["light", str(folder), "--shadow-depth", "3"]) == 0  # deeper creases traced: darker still
    assert "shadow depth 3" in capsys.readouterr().out
    deeper = codes(folder / "composite.png")
    assert (deeper <= occluded).all() and (deeper < occluded).any() and np.array_equal(deeper, composite_of(folder))


def composite_of(folder) -> np.ndarray:
    """The engine's render of the saved stack as 8-bit codes (H, W, 3)."""
    from lasagna.io.render import composite_codes, render_stack

    return composite_codes(render_stack(load_stack(folder)).image).permute(1, 2, 0).numpy().astype(int)


def test_add_light_adds_a_direct_term_and_clear_lights_removes_it(folder, capsys):
    """``--add-light 'LIGHT;COLOUR;K'`` (repeatable) adds lights to the layer's own, each direct term summed (the
    composite against numpy float64); a second call appends; ``--clear-lights`` removes them all, the layer as
    before."""
    assert main(["light", str(folder), "--clear-lights"]) == 0  # none yet: the composite as the layer alone lights it
    first = codes(folder / "composite.png")
    assert main(["light", str(folder), "--add-light", "right;#8080ff;0.5"]) == 0
    assert "1 more light" in capsys.readouterr().out
    assert main(["light", str(folder), "--add-light", "x=0.5,y=0,z=0.5"]) == 0
    extra = json.loads((folder / "stack.json").read_text())["layers"][1]["extra_lights"]
    assert [(e["light"], e["intensity"]) for e in extra] == [("right", 0.5), ("x=0.5,y=0,z=0.5", 1.0)]
    n = read_normals(folder / "layers" / "shape.png")
    _, h, w = n.shape
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    d = np.stack([(0.5 - (jj + 0.5) / w) * w / 16, ((ii + 0.5) / h - 0.0) * h / 16, np.full((h, w), 0.5)])
    r = np.linalg.norm(d, axis=0)
    top = (0.5 / r) ** 2 * np.maximum(0.0, (n * d / r).sum(0))
    c = 0.5 * np.array([128 / 255, 128 / 255, 1.0])
    direct = np.maximum(0.0, np.einsum("chw,c->hw", n, light(180, 60)))[None]
    direct = direct + c[:, None, None] * np.maximum(0.0, np.einsum("chw,c->hw", n, light(0, 60)))[None] + top[None]
    base = codes(folder / "layers" / "base.png").transpose(2, 0, 1) / 255.0
    want = np.clip(base * (0.25 + 0.75 * direct), 0, 1) * 255
    np.testing.assert_allclose(codes(folder / "composite.png").transpose(2, 0, 1), want, atol=0.51)
    assert main(["light", str(folder), "--clear-lights"]) == 0
    assert json.loads((folder / "stack.json").read_text())["layers"][1]["extra_lights"] == []
    np.testing.assert_array_equal(codes(folder / "composite.png"), first)


def edited_relight(tiny, tmp_path, monkeypatch, seed: int):
    """A random 12×16 picture (``tmp_path``/a.png) edited by ``lasagna edit --layer relight --layer-kind surface
    --condition right`` with the tiny catalogue into ``tmp_path``/out; the folder."""
    monkeypatch.setenv("LASAGNA_LAYERS", str(tiny))
    torch.manual_seed(seed)
    picture = (torch.rand(3, 12, 16) * 255).to(torch.uint8)
    Image.fromarray(picture.permute(1, 2, 0).numpy()).save(tmp_path / "a.png")
    out = tmp_path / "out"
    argv = ["edit", str(tmp_path / "a.png"), "--layer", "relight", "--layer-kind", "surface", "--condition", "right"]
    assert main([*argv, "-o", str(out)]) == 0
    return out


def test_read_again_estimates_a_relights_surface_told_its_source_light(tiny, tmp_path, monkeypatch, capsys):
    """``--from L --read-again``: a relight surface layer made by ``lasagna edit`` is estimated again told L — its
    normal map on disk exactly the map of ``lasagna edit --layer-kind surface --from L`` (the preset's told estimator,
    recorded in ``made_by``), the folder's stack.ora kept current. A layer with nothing to read again (a map of
    one's own) is refused in one line, exit 2, the folder unchanged."""
    from lasagna import edit

    out = edited_relight(tiny, tmp_path, monkeypatch, seed=4)
    capsys.readouterr()
    assert main(["light", str(out), "--from", "az=150,el=40", "--read-again"]) == 0
    said = capsys.readouterr().out
    assert "read again by surface-lit-told-32" in said and "from az=150,el=40" in said
    stack = load_stack(out)
    layer = stack.document.layers[-1]
    assert layer.source_light == "az=150,el=40" and layer.made_by["told_estimator"] == "surface-lit-told-32"
    fresh = edit(tmp_path / "a.png", "relight", "right", layer_kind="surface", source_light="az=150,el=40")
    assert np.array_equal(read_normals(out / layer.source), read_normals_of(fresh, tmp_path / "fresh"))
    with zipfile.ZipFile(out / "stack.ora") as z:
        merged = np.asarray(Image.open(io.BytesIO(z.read("mergedimage.png"))).convert("RGB")).astype(int)
    assert np.array_equal(merged, codes(out / "composite.png"))


def test_read_again_within_fuses_a_rough_source_light_as_edit_does(tiny, tmp_path, monkeypatch, capsys):
    """``--from L --within D --read-again``: the layer is read again told L's azimuth and its elevation fused with the
    fit, exactly as ``lasagna edit --from L --within D`` reads it (the same normal map, the same stored source light,
    the reading in ``made_by``); ``--within`` without ``--read-again`` is refused in one line, the folder unchanged."""
    from lasagna import edit

    out = edited_relight(tiny, tmp_path, monkeypatch, seed=5)
    before = (out / "stack.json").read_bytes()
    capsys.readouterr()
    assert main(["light", str(out), "--from", "az=150,el=40", "--within", "10"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "expected --read-again too" in err and (out / "stack.json").read_bytes() == before
    assert main(["light", str(out), "--from", "az=150,el=40", "--within", "10", "--read-again"]) == 0
    layer = load_stack(out).document.layers[-1]
    fresh = edit(
        tmp_path / "a.png", "relight", "right", layer_kind="surface", source_light="az=150,el=40", source_within=10
    )
    want = fresh.stack.document.layer(fresh.layer_id)
    assert layer.source_light == want.source_light and layer.source_light.startswith("az=150,el=")
    assert layer.made_by["source_read"] == "az=150,el=40" and layer.made_by["source_within"] == 10
    assert np.array_equal(read_normals(out / layer.source), read_normals_of(fresh, tmp_path / "fresh"))


def read_normals_of(result, folder) -> np.ndarray:
    result.save(folder)
    return read_normals(folder / result.stack.document.layer(result.layer_id).source)


def test_read_again_refuses_a_map_of_ones_own_in_one_line(folder, capsys):
    before = (folder / "stack.json").read_bytes(), layer_bytes(folder)
    assert main(["light", str(folder), "--from", "top", "--read-again"]) == 2
    err = capsys.readouterr().err
    assert "normal map of one's own" in err and err.count("\n") == 1 and "Traceback" not in err
    assert ((folder / "stack.json").read_bytes(), layer_bytes(folder)) == before
