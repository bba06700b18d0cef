"""PSD export read back with psd-tools: layers, blend modes, opacity, visibility, pixels, the merged
image, and psd-tools' own flattening compared to our composite."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from lasagna.errors import ExportError
from lasagna.export.psd import export_psd
from lasagna.io.render import render_stack
from lasagna.io.stack import Stack, load_stack
from tests.support.reference import composite_reference, to_uint8
from tests.support.stackcraft import random_stack

psd_tools = pytest.importorskip("psd_tools")
from psd_tools import PSDImage  # noqa: E402
from psd_tools.constants import BlendMode  # noqa: E402

BASIC = Path(__file__).resolve().parents[2] / "examples" / "stacks" / "basic"


def test_layers_modes_opacity_visibility_pixels(tmp_path):
    stack = Stack.from_image(torch.randint(0, 256, (3, 12, 16)) / 255.0)
    stack.add_layer(
        "shade", torch.linspace(0.2, 1.8, 16).expand(1, 12, 16).contiguous(), blend="multiply", range=(0, 2)
    )
    paint = torch.randint(0, 256, (4, 5, 6)) / 255.0
    stack.add_layer("paint", paint, opacity=0.4, offset=(3, 2), name="Paint")
    stack.add_layer("glow", torch.full((3, 12, 16), 0.2), blend="plus", visible=False)
    stack.add_layer("haze", torch.full((3, 12, 16), 0.1), blend="screen")
    psd = PSDImage.open(export_psd(stack, tmp_path / "x.psd"))
    layers = list(psd)
    assert [layer.name for layer in layers] == [
        "Background",
        "base",
        "shade",
        "shade (colour dodge: values above 1)",
        "shade (clamp to 1)",
        "Paint",
        "glow",
        "glow (clamp to 1)",
        "haze",
    ]
    assert [layer.blend_mode for layer in layers] == [
        BlendMode.NORMAL,
        BlendMode.NORMAL,
        BlendMode.MULTIPLY,
        BlendMode.COLOR_DODGE,
        BlendMode.DARKEN,
        BlendMode.NORMAL,
        BlendMode.LINEAR_DODGE,
        BlendMode.DARKEN,
        BlendMode.SCREEN,
    ]
    assert layers[5].opacity == round(0.4 * 255) and layers[1].opacity == 255
    assert [layer.visible for layer in layers] == [True] * 6 + [False, False, True]
    assert layers[5].bbox == (3, 2, 9, 7)
    got = np.asarray(layers[5].topil().convert("RGBA")).astype(int)
    want = np.rint(paint.numpy().transpose(1, 2, 0) * 255).astype(int)
    np.testing.assert_array_equal(got, want)
    # The merged image is our composite (the float32 render the export made), not psd-tools' own.
    ours = to_uint8(render_stack(stack).image.double().numpy())
    np.testing.assert_array_equal(np.asarray(psd.topil().convert("RGB")), ours)


@pytest.mark.parametrize("seed", range(3))
def test_psd_tools_flattening_matches(tmp_path, seed):
    """psd-tools' own compositor (8-bit, Photoshop formulas) flattens our layers ≈ our composite."""
    folder = random_stack(tmp_path / "s", 300 + seed, unit_only=True)
    path = export_psd(load_stack(folder), tmp_path / "x.psd")
    flat = np.asarray(PSDImage.open(path).composite(force=True).convert("RGB")).astype(int)
    ours = to_uint8(composite_reference(folder)).astype(int)
    err = np.abs(flat - ours)
    assert err.max() <= 3 and err.mean() <= 0.5, (err.max(), err.mean())


def test_basic_example_with_dodge_pair(tmp_path):
    path = export_psd(load_stack(BASIC), tmp_path / "b.psd")
    flat = np.asarray(PSDImage.open(path).composite(force=True).convert("RGB")).astype(int)
    err = np.abs(flat - to_uint8(composite_reference(BASIC)).astype(int))
    assert err.max() <= 3 and err.mean() <= 0.6, (err.max(), err.mean())


def test_missing_psd_tools_says_how_to_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "psd_tools", None)
    with pytest.raises(ExportError, match=r"pip install 'lasagna-layers\[psd\]'"):
        export_psd(Stack.from_image(torch.rand(3, 2, 2)), tmp_path / "x.psd")
    assert not (tmp_path / "x.psd").exists()


@pytest.mark.parametrize("name", ["名前", "😀", "Ünïcode ✓", "n" * 300, "名" * 200])
def test_any_layer_name_survives(tmp_path, name):
    """The Pascal-string name is MacRoman and at most 255 bytes: it gets a lossy stand-in, and the full name
    goes in the Unicode layer-name block (luni), which psd-tools (like Photoshop) reads in its place."""
    from psd_tools.constants import Tag

    from lasagna.export.psd import pascal_name

    stack = Stack.from_image(torch.rand(3, 4, 5))
    stack.add_layer("glow", torch.full((3, 4, 5), 0.2), blend="plus", name=name)
    psd = PSDImage.open(export_psd(stack, tmp_path / "x.psd"))
    names = [layer.name for layer in psd]
    assert names == ["Background", "base", name, f"{name} (clamp to 1)"]
    record = list(psd)[2]._record
    assert record.tagged_blocks.get_data(Tag.UNICODE_LAYER_NAME) == name
    assert record.name == pascal_name(name) and len(record.name.encode("mac_roman")) <= 255
    assert pascal_name("名前 ü") == "?? ü" and pascal_name("é" * 300) == "é" * 255


def test_japanese_names_from_an_ora_reach_the_psd(tmp_path):
    from lasagna.export.ora import export_ora
    from lasagna.export.ora_import import import_ora

    stack = Stack.from_image(torch.rand(3, 4, 5))
    stack.add_layer("kage", torch.full((1, 4, 5), 0.5), blend="multiply", name="影の層")
    back = import_ora(export_ora(stack, tmp_path / "k.ora"))
    psd = PSDImage.open(export_psd(back, tmp_path / "k.psd"))
    assert "影の層" in [layer.name for layer in psd]


def test_every_mode_has_its_psd_blend_mode(tmp_path):
    from psd_tools.constants import BlendMode

    from lasagna.document.blend import BLEND_MODES
    from lasagna.export.psd_tools_api import psd_blend_modes
    from tests.export.test_ora import _every_mode_stack

    stack = _every_mode_stack(tmp_path / "s")
    psd = PSDImage.open(export_psd(stack, tmp_path / "x.psd"))
    got = {layer.name: layer.blend_mode for layer in psd}
    expect = {m: BlendMode.LINEAR_DODGE if m == "plus" else BlendMode[m.upper().replace("-", "_")] for m in BLEND_MODES}
    assert psd_blend_modes(BlendMode) == expect
    for mode in BLEND_MODES:
        assert got[f"m-{mode}"] == expect[mode]
