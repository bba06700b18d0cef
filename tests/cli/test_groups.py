"""Stacks with nested groups through the CLI and the stack-folder I/O: ``lasagna composite`` against the
independent float64 reference (``tests/support/reference.py``), validate, load/save round trips, one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import torch
from PIL import Image

from lasagna.cli import main
from lasagna.io.render import render_stack
from lasagna.io.stack import load_stack, save_stack
from tests.support.reference import composite_reference, to_uint8
from tests.support.stackcraft import random_group_stack, write_png8, write_stack

ROOT = Path(__file__).resolve().parents[2]


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


# Modes defined outside [0, 1] (clamp="output" keeps intermediates unclamped; soft-light's √Cb and the dodge and
# burn quotients are not, and implementations differ there).
UNBOUNDED = ("normal", "multiply", "plus", "screen", "darken", "lighten", "difference", "exclusion")


@pytest.mark.parametrize("clamp", ["layer", "output"])
@pytest.mark.parametrize("seed", range(12))
def test_composite_of_nested_groups_matches_the_reference(tmp_path, capsys, seed, clamp):
    modes = None if clamp == "layer" else UNBOUNDED
    folder = random_group_stack(tmp_path / "s", seed, clamp=clamp, modes=modes)
    code, out, err = run(capsys, "composite", folder, "-o", tmp_path / "out.png")
    assert code == 0, err
    with Image.open(tmp_path / "out.png") as im:
        got = np.asarray(im).astype(int)
    ref = composite_reference(folder)
    assert np.abs(got - to_uint8(ref).astype(int)).max() <= 1
    # In float64 from the decoded PNGs (float32 values: ~3e-8 from the reference's float64 reads).
    exact = render_stack(load_stack(folder), dtype=torch.float64).image.numpy()
    assert np.abs(exact - ref).max() < 1e-6


def test_stack_json_with_groups_is_valid_against_the_schema(tmp_path):
    folder = random_group_stack(tmp_path / "s", 3)
    schema = json.loads((ROOT / "schemas" / "stack.schema.json").read_text())
    jsonschema.validate(json.loads((folder / "stack.json").read_text()), schema)
    bad = json.loads((folder / "stack.json").read_text())
    bad["layers"].append({"id": "pt", "kind": "group", "blend": "multiply", "layers": []})
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, schema)


def test_validate_counts_every_layer(tmp_path, capsys):
    folder = random_group_stack(tmp_path / "s", 4)
    doc = json.loads((folder / "stack.json").read_text())

    def count(layers):
        return sum(1 + count(x.get("layers", [])) for x in layers)

    code, out, _ = run(capsys, "validate", folder)
    assert code == 0 and out.startswith(f"ok: {count(doc['layers'])} layers")


def test_save_and_load_round_trip_keeps_document_and_group_masks(tmp_path):
    folder = random_group_stack(tmp_path / "s", 5)
    stack = load_stack(folder)
    save_stack(stack, tmp_path / "copy")
    again = load_stack(tmp_path / "copy")
    assert again.document == stack.document
    for id, t in stack.tensors.items():
        assert np.array_equal(t.mask is None, again.tensors[id].mask is None)
        if t.mask is not None:
            assert np.allclose(t.mask.numpy(), again.tensors[id].mask.numpy(), atol=0.5 / 255)
    assert np.array_equal(render_stack(stack).image.numpy(), render_stack(again).image.numpy())


def _doc(layers, w=4, h=4):
    return {"format": "lasagna.stack", "version": 1, "canvas": {"width": w, "height": h}, "layers": layers}


def test_errors_are_one_line_naming_the_nested_place(tmp_path, capsys):
    base = {"id": "base", "kind": "solid", "color": [0.5, 0.5, 0.5]}
    folder = write_stack(
        tmp_path / "a",
        _doc([base, {"id": "g", "kind": "group", "layers": [{"id": "p", "kind": "pixels", "source": "layers/p.png"}]}]),
    )
    code, _, err = run(capsys, "composite", folder, "-o", tmp_path / "o.png")
    assert code == 2 and err.count("\n") == 1
    assert "layers[1].layers[0].source: 'layers/p.png' does not exist" in err

    folder = write_stack(tmp_path / "b", _doc([base, {"id": "g", "kind": "group", "blend": "screen", "layers": []}]))
    code, _, err = run(capsys, "validate", folder)
    assert code == 2 and err.count("\n") == 1
    assert "layers[1].blend: group 'g' passes through (isolated: false) with blend 'screen'" in err

    write_png8(tmp_path / "c/masks/g.png", np.zeros((2, 2, 3), np.uint8) + np.array([0, 255, 0], np.uint8))
    folder = write_stack(
        tmp_path / "c",
        _doc([base, {"id": "g", "kind": "group", "isolated": True, "mask": "masks/g.png", "layers": []}]),
    )
    code, _, err = run(capsys, "composite", folder, "-o", tmp_path / "o.png")
    assert code == 2 and err.count("\n") == 1 and "layers[1].mask (masks/g.png): mask is a colour image" in err

    folder = write_stack(
        tmp_path / "d", _doc([base, {"id": "g", "kind": "group", "mask": "../outside.png", "layers": []}])
    )
    code, _, err = run(capsys, "composite", folder, "-o", tmp_path / "o.png")
    assert code == 2 and err.count("\n") == 1 and "escapes the stack folder" in err


def test_composite_verbose_lists_nested_skips(tmp_path, capsys):
    base = {"id": "base", "kind": "solid", "color": [0.5, 0.5, 0.5]}
    hidden = {"id": "h", "kind": "solid", "color": [1.0, 0.0, 0.0], "visible": False}
    inner = {"id": "in", "kind": "solid", "color": [0.0, 1.0, 0.0], "blend": "multiply"}
    group = {
        "id": "g",
        "kind": "group",
        "isolated": True,
        "blend": "difference",
        "opacity": 0.5,
        "layers": [hidden, inner],
    }
    folder = write_stack(tmp_path / "s", _doc([base, group]))
    code, out, err = run(capsys, "composite", folder, "-o", tmp_path / "o.png", "-v")
    assert code == 0, err
    assert "2 of 4 layers composed" not in out  # base, g, in are composed
    assert "3 of 4 layers composed" in out and "skipped: h: hidden" in out
    with Image.open(tmp_path / "o.png") as im:
        got = np.asarray(im)[0, 0].astype(int)
    # |0.5 − (0, 1, 0)| = (0.5, 0.5, 0.5), mixed half-way with 0.5: all 0.5
    assert np.abs(got - 128).max() <= 1
