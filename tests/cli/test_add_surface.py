"""``lasagna add-surface``: a normal map of one's own added as a surface layer — the composite against numpy float64
Lambert of the map's own codes (8-bit, OpenGL +Y up; a DirectX map's green flipped), the other layers' PNGs
untouched, the folder's stack.ora kept current, and hostile input (one line, exit 2, nothing changed)."""

from __future__ import annotations

import io
import json
import math
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
