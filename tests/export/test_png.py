"""Per-layer PNG export: raw stored values (never min–max normalised), 16-bit for ranged layers,
masks, solid and unrendered learned layers, and the layers.json index."""

from __future__ import annotations

import json

import numpy as np
import torch

from lasagna.export.png import export_layer_pngs
from lasagna.io.stack import NOT_RENDERED, Stack
from tests.support.reference import read_png64


def test_raw_values_depths_and_index(tmp_path):
    stack = Stack.from_image(0.2 + 0.1 * torch.rand(3, 6, 8))  # values in [0.2, 0.3]: must stay there
    shade = 0.5 + torch.rand(1, 6, 8)  # [0.5, 1.5] in a [0, 2] range
    stack.add_layer("shade", shade, blend="multiply", range=(0, 2), mask=torch.full((1, 6, 8), 0.5))
    stack.add_solid("sun", (1.0, 0.5, 0.25), blend="plus", range=(0, 2), size=(3, 2), offset=(1, 1))
    stack.document = stack.document.with_layer(
        {
            "id": "relit",
            "kind": "learned",
            "preset": "shading",
            "condition": {"label": "left"},
            "conditioned_on": "base",
            "blend": "multiply",
        }
    )
    files = export_layer_pngs(stack, tmp_path / "out")
    names = sorted(str(p.relative_to(tmp_path / "out")) for p in files)
    assert names == ["base.png", "layers.json", "masks/shade.png", "shade.png", "sun.png"]

    base, _ = read_png64(tmp_path / "out/base.png")
    assert 0.19 < base.min() and base.max() < 0.31  # not stretched to [0, 1]
    np.testing.assert_allclose(base, stack.tensors["base"].color.double().numpy(), atol=0.5 / 255 + 1e-7)
    stored, _ = read_png64(tmp_path / "out/shade.png")
    np.testing.assert_allclose(stored, shade.double().numpy() / 2, atol=0.5 / 65535 + 1e-7)  # v = y / 2, 16-bit
    sun, _ = read_png64(tmp_path / "out/sun.png")
    # A solid colour is already a stored value v (the document maps it by the range, like a PNG).
    assert sun.shape == (3, 2, 3) and np.allclose(sun[:, 0, 0], [1.0, 0.5, 0.25], atol=1e-4)

    meta = json.loads((tmp_path / "out/layers.json").read_text())
    by_id = {layer["id"]: layer for layer in meta["layers"]}
    assert [layer["id"] for layer in meta["layers"]] == ["base", "shade", "sun", "relit"]
    assert by_id["shade"]["bit_depth"] == 16 and by_id["base"]["bit_depth"] == 8
    assert by_id["shade"]["range"] == [0.0, 2.0] and by_id["shade"]["mask"] == "masks/shade.png"
    assert by_id["relit"]["file"] is None and by_id["relit"]["note"] == NOT_RENDERED
    assert by_id["sun"]["offset"] == {"x": 1, "y": 1}


def test_a_surface_layer_is_its_normal_map_with_what_lights_it(tmp_path):
    """A surface layer's file is its stored 16-bit normal map; the index's ``surface`` record names the convention
    and every render field, and lighting the file by them (numpy float64: n = 2v − 1 renormalised, Lambert with
    the record's ambient, colour and intensity) gives the stack's render of the layer within one 16-bit code."""
    from lasagna.compose.surface import layer_surface_tensors, normals_from_height

    stack = Stack.from_image(torch.full((3, 12, 16), 0.5))
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, 12), torch.linspace(-1, 1, 16), indexing="ij")
    stack.add_surface("shape", normals_from_height((0.4 * torch.exp(-3 * (xx**2 + yy**2)))[None, None])[0], "left")
    stack.set_light("shape", "az=150,el=40", ambient=0.3, light_color=(1.0, 0.8, 0.6), light_intensity=1.2)
    export_layer_pngs(stack, tmp_path / "out")
    entry = json.loads((tmp_path / "out/layers.json").read_text())["layers"][1]
    record = entry["surface"]
    assert entry["file"] == "shape.png" and entry["bit_depth"] == 16 and "+Y up" in record["normal_map"]
    assert (record["light"], record["ambient"], record["light_intensity"]) == ("az=150,el=40", 0.3, 1.2)
    assert record["light_color"] == [1.0, 0.8, 0.6] and record["shadows"] == 0.0 and record["relief"] == 1.0
    v, _ = read_png64(tmp_path / "out/shape.png")
    n = 2 * v - 1
    n /= np.linalg.norm(n, axis=0, keepdims=True)
    az, el = np.radians(150), np.radians(40)
    light = np.array([np.sin(el) * np.cos(az), np.sin(el) * np.sin(az), np.cos(el)])
    direct = np.maximum(0.0, np.einsum("chw,c->hw", n, light))
    want = 0.3 + 0.7 * 1.2 * np.asarray(record["light_color"])[:, None, None] * direct
    got = layer_surface_tensors(stack.tensors["shape"], stack.document.layer("shape"))[0].color.double().numpy()
    np.testing.assert_allclose(got, want, atol=1 / 65535 + 1e-6)
