"""``lasagna add-surface``: a normal map of one's own added as a surface layer — the composite against numpy float64
Lambert of the map's own codes (8-bit, OpenGL +Y up; a DirectX map's green flipped), the other layers' PNGs
untouched, the folder's stack.ora kept current, and hostile input (one line, exit 2, nothing changed)."""

from __future__ import annotations

import io
import json
import math
import re
import zipfile

import numpy as np
import pytest
import torch
from PIL import Image

from lasagna.cli import main
from lasagna.export.ora import encode_ora
from lasagna.io.stack import Stack, load_stack


def light(az: float, el: float) -> np.ndarray:
    a, e = math.radians(az), math.radians(el)
    return np.array([math.sin(e) * math.cos(a), math.sin(e) * math.sin(a), math.cos(e)])


def codes(path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB")).astype(int)


@pytest.fixture
def folder(tmp_path):
    torch.manual_seed(5)
    s = Stack.from_image((torch.rand(3, 10, 14) * 255).to(torch.uint8))
    out = tmp_path / "s"
    s.save(out)
    (out / "stack.ora").write_bytes(encode_ora(load_stack(out)))
    return out


@pytest.fixture
def bumps(tmp_path) -> tuple[np.ndarray, object]:
    """An 8-bit OpenGL normal map of a bump (8 × 12), its codes (h, w, 3) and its path."""
    yy, xx = np.mgrid[0:8, 0:12]
    n = np.stack([(xx - 5.5) / 9, -(yy - 3.5) / 7, np.ones((8, 12))], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    c = np.round((n + 1) / 2 * 255).astype(np.uint8)
    path = tmp_path / "bumps.png"
    Image.fromarray(c).save(path)
    return c, path


def lambert_of_codes(c: np.ndarray, az: float, el: float) -> np.ndarray:
    n = c.astype(np.float64) / 255 * 2 - 1
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return 0.25 + 0.75 * np.maximum(0.0, n @ light(az, el))


def test_a_normal_map_becomes_a_surface_layer_lit_as_its_codes_say(folder, bumps, capsys):
    c, path = bumps
    before = {p.name: p.read_bytes() for p in (folder / "layers").iterdir()}
    assert main(["add-surface", str(folder), str(path), "--light", "az=30,el=50", "--offset", "2,1"]) == 0
    assert "added surface layer bumps (12x8, light az=30,el=50)" in capsys.readouterr().out
    doc = json.loads((folder / "stack.json").read_text())
    layer = doc["layers"][1]
    assert (layer["kind"], layer["id"], layer["offset"], layer["light"]) == (
        "surface",
        "bumps",
        {"x": 2, "y": 1},
        "az=30,el=50",
    )
    after = {p.name: p.read_bytes() for p in (folder / "layers").iterdir()}
    assert {k: v for k, v in after.items() if k in before} == before and set(after) - set(before) == {"bumps.png"}
    base = codes(folder / "layers" / "base.png").astype(np.float64) / 255
    want = base.copy()
    want[1:9, 2:14] *= lambert_of_codes(c, 30, 50)[..., None]
    np.testing.assert_allclose(codes(folder / "composite.png"), np.clip(want, 0, 1) * 255, atol=0.51)
    with zipfile.ZipFile(folder / "stack.ora") as z:  # the folder's ORA flattens to the new composite
        merged = np.asarray(Image.open(io.BytesIO(z.read("mergedimage.png"))).convert("RGB")).astype(int)
    np.testing.assert_array_equal(merged, codes(folder / "composite.png"))
    assert main(["validate", str(folder)]) == 0


def test_a_directx_map_is_read_with_its_green_flipped(folder, bumps, tmp_path):
    c, path = bumps
    flipped = c.copy()
    flipped[..., 1] = 255 - flipped[..., 1]
    Image.fromarray(flipped).save(tmp_path / "dx.png")
    assert main(["add-surface", str(folder), str(path), "--id", "gl"]) == 0
    gl = load_stack(folder).tensors["gl"].color
    assert main(["add-surface", str(folder), str(tmp_path / "dx.png"), "--id", "dx", "--directx"]) == 0
    dx = load_stack(folder).tensors["dx"].color
    assert (gl - dx).abs().max() <= 1.5 / 65535  # the same normals, to the stored map's 16-bit step


@pytest.mark.parametrize(
    "argv, message",
    [
        (["MAP", "--offset", "1"], "--offset: got '1'; expected X,Y in integer pixels"),
        (["MAP", "--light", "up"], "expected one of left"),
        (["MAP", "--id", "base"], "--id: the stack already has a layer 'base'; expected a new id"),
        (["MAP", "--from", "left", "--ambient", "0"], "expected ambient > 0"),
        (["GRAY"], "has 1 colour channel(s); expected an RGB normal map"),
        (["JPEG"], "not a PNG; expected a normal map as an 8- or 16-bit RGB PNG"),
        (["MISSING"], "missing.png"),
        (["GRAY", "--height", "0"], "height: got a depth of 0.0; expected the pixels white stands above black"),
        (["GRAY", "--height", "nan"], "height: got a depth of nan"),
        (["GRAY", "--height", "4", "--directx"], "--directx: a height map has no green to flip"),
        (["JPEG", "--height", "4"], "not a PNG; expected a height map as an 8- or 16-bit grey PNG"),
    ],
)
def test_bad_input_is_one_line_exit_2_and_changes_nothing(folder, bumps, tmp_path, capsys, argv, message):
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(tmp_path / "gray.png")
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / "n.jpg")
    paths = {"MAP": str(bumps[1]), "GRAY": str(tmp_path / "gray.png"), "JPEG": str(tmp_path / "n.jpg")}
    paths["MISSING"] = str(tmp_path / "missing.png")
    before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    assert main(["add-surface", str(folder), *(paths.get(a, a) for a in argv)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err, err
    assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} == before


def test_a_height_map_becomes_the_surface_of_its_slopes(folder, tmp_path, capsys):
    """``--height PX``: a grey PNG read as heights, white PX pixels above black; the layer's normals are the slopes
    of those heights (numpy float64 central differences, as a bump map lights in Lighting Effects), and the composite
    is their Lambert shading; an RGB grey map reads the same."""
    yy, xx = np.mgrid[0:10, 0:14]
    grey = np.clip(1 - ((xx - 6.5) ** 2 + (yy - 4.5) ** 2) / 30, 0, 1)  # a dome, 1 at its top
    codes16 = np.round(grey * 65535).astype(np.uint16)
    Image.fromarray(codes16).save(tmp_path / "h16.png")
    assert main(["add-surface", str(folder), str(tmp_path / "h16.png"), "--height", "3", "--light", "az=20,el=50"]) == 0
    assert "added surface layer h16" in capsys.readouterr().out
    h = codes16.astype(np.float64) / 65535 * 3  # pixels
    d_row, d_col = np.gradient(h)
    n = np.stack([-d_col, d_row, np.ones_like(h)])
    n /= np.linalg.norm(n, axis=0, keepdims=True)
    stored = load_stack(folder).tensors["h16"].color.double().numpy() * 2 - 1
    stored /= np.linalg.norm(stored, axis=0, keepdims=True)
    assert np.abs(stored - n).max() <= 3e-4  # the 16-bit map's step
    base = codes(folder / "layers" / "base.png").transpose(2, 0, 1) / 255
    shade = 0.25 + 0.75 * np.maximum(0.0, np.einsum("chw,c->hw", n, light(20, 50)))
    np.testing.assert_allclose(
        codes(folder / "composite.png").transpose(2, 0, 1), np.clip(base * shade, 0, 1) * 255, atol=0.6
    )
    rgb = np.repeat(np.round(grey * 255).astype(np.uint8)[..., None], 3, -1)
    Image.fromarray(rgb).save(tmp_path / "h8.png")
    assert main(["add-surface", str(folder), str(tmp_path / "h8.png"), "--height", "3", "--id", "h8"]) == 0
    eight = load_stack(folder).tensors["h8"].color.double().numpy()
    assert np.abs(eight - load_stack(folder).tensors["h16"].color.double().numpy()).max() < 0.01


def test_an_exported_height_map_comes_back_as_its_surface(tmp_path, capsys):
    """A round trip: a surface layer's height map (`lasagna export --height-map`, which prints its depth in pixels)
    added back with ``--height`` that depth gives the layer's normals again (mean angle under 2°, off the border)."""
    from lasagna.compose.surface import normals_from_height

    yy, xx = torch.meshgrid(torch.arange(40.0), torch.arange(56.0), indexing="ij")
    bump = 0.2 * torch.exp(-((xx - 20) ** 2 + (yy - 18) ** 2) / 60) + 0.1 * torch.exp(
        -((xx - 40) ** 2 + (yy - 25) ** 2) / 30
    )
    s = Stack.from_image(torch.full((3, 40, 56), 128, dtype=torch.uint8))
    s.add_surface("shape", normals_from_height(bump[None, None])[0], "left")
    out = tmp_path / "s"
    s.save(out)
    assert main(["export", str(out), "--height-map", str(tmp_path / "h.png")]) == 0
    said = capsys.readouterr().out
    match = re.search(r"white ([0-9.]+) pixels above it", said)
    depth = float(match.group(1)) if match else None
    assert depth is not None and depth > 1, said
    assert main(["add-surface", str(out), str(tmp_path / "h.png"), "--height", str(depth), "--id", "back"]) == 0
    stack = load_stack(out)
    a = stack.tensors["shape"].color.double() * 2 - 1
    b = stack.tensors["back"].color.double() * 2 - 1
    cos = (torch.nn.functional.normalize(a, dim=0) * torch.nn.functional.normalize(b, dim=0)).sum(0).clamp(-1, 1)
    angle = torch.rad2deg(torch.acos(cos))[2:-2, 2:-2]
    assert float(angle.mean()) < 2.0 and float(angle.max()) < 8.0, (float(angle.mean()), float(angle.max()))
