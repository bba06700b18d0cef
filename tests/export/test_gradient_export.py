"""Gradient layers leave Lasagna as pixels: PSD (flattened by psd-tools) and ORA carry the fill's pixels with one
warning that the live fill is not written; a masked gradient inside an offset group saves and loads bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.document import Document
from lasagna.export.ora import export_ora
from lasagna.export.png import layer_pngs
from lasagna.io.render import render_stack
from lasagna.io.stack import Stack, load_stack

W, H = 12, 9
STOPS = [{"location": 0.0, "color": [0.9, 0.2, 0.1]}, {"location": 1.0, "color": [0.1, 0.3, 0.9], "midpoint": 0.5}]


def _stack() -> Stack:
    rng = np.random.default_rng(3)
    base = (rng.integers(0, 256, (3, H, W)) / 255).astype(np.float32)  # 8-bit codes: saved exactly
    doc = Document.from_dict(
        {
            "format": "lasagna.stack",
            "version": 1,
            "canvas": {"width": W, "height": H, "background": [1.0, 1.0, 1.0]},
            "layers": [{"id": "base", "kind": "pixels", "source": "layers/base.png"}],
        }
    )
    stack = Stack(doc)
    stack.set_pixels("base", torch.from_numpy(base))
    stack.document = stack.document.with_layer({"id": "grp", "kind": "group", "offset": {"x": 2, "y": 1}, "layers": []})
    opacity = [{"location": 0.0, "opacity": 1.0}, {"location": 1.0, "opacity": 0.3}]
    gradient = {"style": "diamond", "angle": 20.0, "align": False, "stops": STOPS, "opacity_stops": opacity}
    mask = torch.from_numpy((rng.integers(0, 256, (1, 5, 7)) / 255).astype(np.float32))
    stack.add_gradient("g", gradient, mask=mask, blend="multiply", opacity=0.8, size=(7, 5), offset=(1, 2))
    g = stack.document.layer("g").model_dump()
    stack.document = stack.document.without_layer("g").replace_layer("grp", layers=[g])
    return stack


def test_a_masked_gradient_in_a_group_saves_and_loads_bit_for_bit(tmp_path):
    stack = _stack()
    before = render_stack(stack, dtype=torch.float64).image
    stack.save(tmp_path / "s")
    loaded = load_stack(tmp_path / "s")
    assert loaded.document.layer("g").kind == "gradient" and loaded.document.layer("g").mask == "masks/g.png"
    after = render_stack(loaded, dtype=torch.float64).image
    assert torch.equal(after, before)
    files, meta = layer_pngs(loaded)
    assert "g.png" in files and "masks/g.png" in files
    assert [e["gradient"]["style"] for e in meta["layers"] if e["id"] == "g"] == ["diamond"]


def test_psd_and_ora_hold_the_pixels_with_one_warning(tmp_path):
    psd_tools = pytest.importorskip("psd_tools")
    from lasagna.export.psd import export_psd

    stack = _stack()
    ours = render_stack(stack, dtype=torch.float64).image.numpy().transpose(1, 2, 0)
    for name, export in (("s.psd", export_psd), ("s.ora", export_ora)):
        warnings: list[str] = []
        export(stack, tmp_path / name, warn=warnings.append)
        fills = [w for w in warnings if "gradient" in w]
        assert len(fills) == 1 and "live gradient fill is not written" in fills[0]
    flat = psd_tools.PSDImage.open(tmp_path / "s.psd").composite(force=True).convert("RGB")
    assert np.abs(np.asarray(flat, dtype=np.float64) - np.rint(ours * 255)).max() <= 2
