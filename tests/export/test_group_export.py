"""Exporting stacks with groups (ORA, PSD, per-layer PNGs) until nested export exists: nothing is lost
silently. Pass-through groups of opacity 1 are their layers (written flat, exact); any other group is
written flat with a warning line and the exact composite on top, so every file flattens to our image."""

from __future__ import annotations

import io
import json
import zipfile
from xml.etree import ElementTree as ET

import numpy as np
import pytest

from lasagna.export.ora import encode_ora, import_ora
from lasagna.export.png import export_layer_pngs
from lasagna.io.render import render_stack
from lasagna.io.stack import load_stack
from tests.export.oraflat import read_png_rgb
from tests.stackcraft import random_group_stack, write_png8, write_stack


def _doc(layers):
    return {"format": "lasagna.stack", "version": 1, "canvas": {"width": 6, "height": 5}, "layers": layers}


def test_pass_through_groups_of_opacity_one_export_flat_and_exact(tmp_path):
    write_png8(tmp_path / "s/layers/a.png", np.random.default_rng(0).integers(0, 256, (3, 4, 3)))
    inner = {"id": "a", "kind": "pixels", "source": "layers/a.png", "blend": "multiply", "offset": {"x": 1, "y": 1}}
    group = {"id": "g", "kind": "group", "offset": {"x": 1, "y": 0}, "layers": [inner]}
    folder = write_stack(tmp_path / "s", _doc([{"id": "base", "kind": "solid", "color": [0.5, 0.6, 0.7]}, group]))
    stack = load_stack(folder)
    warnings: list[str] = []
    data = encode_ora(stack, warn=warnings.append)
    assert warnings == []
    (tmp_path / "f.ora").write_bytes(data)
    back = import_ora(tmp_path / "f.ora")
    assert back.document.layer("a").offset.x == 2  # the group's offset added
    ours = np.rint(np.clip(render_stack(stack).image.numpy(), 0, 1) * 255)
    theirs = np.rint(np.clip(render_stack(back).image.numpy(), 0, 1) * 255)
    assert np.abs(ours - theirs).max() <= 1


@pytest.mark.parametrize("seed", range(4))
def test_other_groups_warn_and_keep_the_exact_composite(tmp_path, seed):
    folder = random_group_stack(tmp_path / "s", seed)
    stack = load_stack(folder)
    warnings: list[str] = []
    data = encode_ora(stack, warn=warnings.append)
    doc = stack.document
    other = [
        layer
        for _, layer in doc.walk()
        if layer.kind == "group" and (layer.isolated or layer.opacity != 1.0 or layer.mask is not None)
    ]
    if other:
        assert len(warnings) == 1 and "group" in warnings[0] and "Composite (exact)" in warnings[0]
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        top = list(ET.fromstring(zf.read("stack.xml")).find("stack"))[0]
        if other:  # the file flattens to the exact composite, whatever a reader makes of the flat layers
            assert top.get("name") == "Composite (exact)"
            flat = np.rint(read_png_rgb(zf.read(top.get("src"))) * 255)
            ours = np.rint(np.clip(render_stack(stack).image.numpy(), 0, 1) * 255).transpose(1, 2, 0)
            assert np.abs(flat - ours).max() <= 1
        else:
            assert warnings == [] or "group" not in warnings[0]


def test_layer_pngs_list_groups(tmp_path):
    folder = random_group_stack(tmp_path / "s", 2)
    stack = load_stack(folder)
    export_layer_pngs(stack, tmp_path / "out")
    index = json.loads((tmp_path / "out" / "layers.json").read_text())
    assert [e["id"] for e in index["layers"]] == list(stack.document.all_ids)
    assert all(e["kind"] != "group" or e["file"] is None for e in index["layers"])
