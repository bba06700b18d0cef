"""Exporting stacks with groups (ORA, PSD, per-layer PNGs): nothing is lost silently. OpenRaster nests every
group (a <stack> with isolation "isolate" or "auto"), PSD writes group records (PASS_THROUGH or the group's
mode); import-ora and import-psd read them back. What a format cannot hold (group masks, pass-through opacity
below 1) gets one warning line and the exact composite on top, so every file flattens to our image."""

from __future__ import annotations

import io
import json
import zipfile
from xml.etree import ElementTree as ET

import numpy as np
import pytest

from lasagna.export.ora import encode_ora
from lasagna.export.ora_import import import_ora
from lasagna.export.png import export_layer_pngs
from lasagna.io.render import render_stack
from lasagna.io.stack import load_stack
from lasagna.limits import MAX_GROUP_DEPTH
from tests.export.oraflat import read_png_rgb
from tests.support.stackcraft import random_group_stack, write_png8, write_stack


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


def _groups(doc) -> list[tuple]:
    """Each group's depth and fields, depth first (a layer wholly off the canvas is not written, so children
    are not counted)."""
    return [
        (path.count("layers"), layer.isolated, layer.blend, round(255 * layer.opacity), layer.visible)  # PSD: 8 bits
        for path, layer in doc.walk()
        if layer.kind == "group"
    ]


def _stacks(el, depth: int = 0):
    for child in el:
        if child.tag == "stack":
            yield depth + 1, child
            yield from _stacks(child, depth + 1)


@pytest.mark.parametrize("seed", range(6))
def test_ora_nests_groups_and_imports_them_back(tmp_path, seed):
    folder = random_group_stack(tmp_path / "s", seed)
    stack = load_stack(folder)
    warnings: list[str] = []
    data = encode_ora(stack, warn=warnings.append)
    doc = stack.document
    groups = [layer for _, layer in doc.walk() if layer.kind == "group"]
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        root = ET.fromstring(zf.read("stack.xml")).find("stack")
        stacks = list(_stacks(root))
        assert len(stacks) == len(groups)  # one nested <stack> per group, in document order (topmost first)
        for _, el in stacks:
            assert el.get("isolation") in ("isolate", "auto") and el.get("x") == el.get("y") == "0"
        inexact = [
            g for g in groups if g.mask is not None or (not g.isolated and g.opacity != 1.0)
        ]  # what OpenRaster cannot hold
        if inexact:
            assert len(warnings) == 1 and "Composite (exact)" in warnings[0]
            assert all(repr(g.id) in warnings[0] for g in inexact)
        top = list(root)[0]
        if warnings:  # the file flattens to the exact composite, whatever a reader makes of the layers
            assert top.get("name") == "Composite (exact)"
            flat = np.rint(read_png_rgb(zf.read(top.get("src"))) * 255)
            ours = np.rint(np.clip(render_stack(stack).image.numpy(), 0, 1) * 255).transpose(1, 2, 0)
            assert np.abs(flat - ours).max() <= 1
    (tmp_path / "f.ora").write_bytes(data)
    back = import_ora(tmp_path / "f.ora")
    assert _groups(back.document) == _groups(doc)  # the same groups, nested the same way
    if not warnings:  # exact: the imported stack composes to ours (layer alpha × mask rounded to 8 bits)
        ours = np.rint(np.clip(render_stack(stack).image.numpy(), 0, 1) * 255)
        theirs = np.rint(np.clip(render_stack(back).image.numpy(), 0, 1) * 255)
        assert np.abs(ours - theirs).max() <= 2


def test_ora_group_fields_and_refusals(tmp_path):
    write_png8(tmp_path / "s/layers/a.png", np.random.default_rng(1).integers(0, 256, (4, 5, 4)))
    inner = {"id": "a", "kind": "pixels", "source": "layers/a.png", "blend": "screen"}
    iso = {"id": "iso", "kind": "group", "isolated": True, "blend": "multiply", "opacity": 0.5, "layers": [inner]}
    hidden = {"id": "pt", "kind": "group", "visible": False, "layers": [iso]}
    base = {"id": "base", "kind": "solid", "color": [0.5, 0.6, 0.7]}
    stack = load_stack(write_stack(tmp_path / "s", _doc([base, hidden])))
    data = encode_ora(stack)
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        root = ET.fromstring(zf.read("stack.xml")).find("stack")
    (pt,) = [el for el in root if el.tag == "stack"]
    (iso_el,) = [el for el in pt if el.tag == "stack"]
    assert (pt.get("isolation"), pt.get("visibility"), pt.get("composite-op")) == ("auto", "hidden", "svg:src-over")
    assert (iso_el.get("isolation"), iso_el.get("composite-op"), float(iso_el.get("opacity"))) == (
        "isolate",
        "svg:multiply",
        0.5,
    )
    # A stack nested past the limit is refused in one line, naming where.
    deep = "".join('<stack name="g">' for _ in range(40)) + '<layer src="data/a.png"/>' + "</stack>" * 40
    xml = f'<image w="4" h="4"><stack>{deep}</stack></image>'
    with zipfile.ZipFile(tmp_path / "deep.ora", "w") as zf:
        zf.writestr("mimetype", "image/openraster")
        zf.writestr("stack.xml", xml)
    with pytest.raises(Exception, match=f"groups nest deeper than {MAX_GROUP_DEPTH}") as err:
        import_ora(tmp_path / "deep.ora")
    assert "\n" not in str(err.value)


def test_layer_pngs_list_groups(tmp_path):
    folder = random_group_stack(tmp_path / "s", 2)
    stack = load_stack(folder)
    export_layer_pngs(stack, tmp_path / "out")
    index = json.loads((tmp_path / "out" / "layers.json").read_text())
    assert [e["id"] for e in index["layers"]] == list(stack.document.all_ids)
    assert all(e["kind"] != "group" or e["file"] is None for e in index["layers"])


@pytest.mark.parametrize("seed", range(4))
def test_psd_keeps_groups_and_import_psd_reads_them_back(tmp_path, seed):
    pytest.importorskip("psd_tools")
    from lasagna.export.psd import encode_psd
    from lasagna.export.psd_import import read_psd

    folder = random_group_stack(tmp_path / "s", seed)
    stack = load_stack(folder)
    warnings: list[str] = []
    (tmp_path / "f.psd").write_bytes(encode_psd(stack, warn=warnings.append))
    back = read_psd(tmp_path / "f.psd", warn=lambda line: None)
    assert _groups(back.document) == _groups(stack.document)
    if not warnings:
        ours = np.rint(np.clip(render_stack(stack).image.numpy(), 0, 1) * 255)
        theirs = np.rint(np.clip(render_stack(back).image.numpy(), 0, 1) * 255)
        assert np.abs(ours - theirs).max() <= 2


def _exact_group_stack(folder, seed):
    """A random group stack with what both formats hold exactly: no group masks, pass-through groups at
    opacity 1, no plus layers (their alpha is baked against an opaque backdrop)."""
    from tests.support.stackcraft import BLEND_NAMES

    random_group_stack(folder, seed, modes=[m for m in BLEND_NAMES if m != "plus"])
    doc = json.loads((folder / "stack.json").read_text())

    def fix(layers):
        for layer in layers:
            if layer["kind"] == "group":
                layer.pop("mask", None)
                if not layer["isolated"]:
                    layer["opacity"] = 1.0
                fix(layer["layers"])

    fix(doc["layers"])
    (folder / "stack.json").write_text(json.dumps(doc))
    return load_stack(folder)


@pytest.mark.parametrize("fmt", ["ora", "psd"])
@pytest.mark.parametrize("seed", range(5))
def test_groups_both_formats_hold_export_exactly(tmp_path, seed, fmt):
    stack = _exact_group_stack(tmp_path / "s", seed)
    assert any(layer.kind == "group" for _, layer in stack.document.walk())
    warnings: list[str] = []
    if fmt == "ora":
        (tmp_path / "f.ora").write_bytes(encode_ora(stack, warn=warnings.append))
        back = import_ora(tmp_path / "f.ora")
    else:
        pytest.importorskip("psd_tools")
        from lasagna.export.psd import encode_psd
        from lasagna.export.psd_import import read_psd

        (tmp_path / "f.psd").write_bytes(encode_psd(stack, warn=warnings.append))
        back = read_psd(tmp_path / "f.psd", warn=lambda line: None)
    assert warnings == []
    assert _groups(back.document) == _groups(stack.document)
    ours = np.rint(np.clip(render_stack(stack).image.numpy(), 0, 1) * 255)
    theirs = np.rint(np.clip(render_stack(back).image.numpy(), 0, 1) * 255)
    assert np.abs(ours - theirs).max() <= 2  # layer alpha × mask and group opacity rounded to 8 bits
