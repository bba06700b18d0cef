"""Pattern layers leave Lasagna as pixels: PSD (flattened by psd-tools) and ORA carry the fill's pixels with one
warning that the live fill is not written; per-layer PNGs write the fill and keep the ``pattern`` record."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.document import Document
from lasagna.export.ora import export_ora
from lasagna.export.png import layer_pngs
from lasagna.io.render import render_stack
from lasagna.io.stack import Stack

W, H = 12, 9


def _stack() -> Stack:
    rng = np.random.default_rng(5)
    doc = Document.from_dict(
        {
            "format": "lasagna.stack",
            "version": 1,
            "canvas": {"width": W, "height": H, "background": [1.0, 1.0, 1.0]},
            "layers": [{"id": "base", "kind": "pixels", "source": "layers/base.png"}],
        }
    )
    stack = Stack(doc)
    stack.set_pixels("base", torch.from_numpy((rng.integers(0, 256, (3, H, W)) / 255).astype(np.float32)))
    stack.document = stack.document.with_layer({"id": "grp", "kind": "group", "offset": {"x": 2, "y": 1}, "layers": []})
    tile = rng.integers(0, 256, (3, 4, 5), dtype=np.uint8)
    mask = rng.integers(0, 256, (5, 7), dtype=np.uint8)
    pattern = {"scale": 150.0, "phase": [1, 2], "align": False}
    stack.add_pattern("p", tile, pattern, mask=mask, blend="multiply", opacity=0.8, size=(7, 5), offset=(1, 2))
    p, t = stack.document.layer("p").model_dump(), stack.tensors["p"]
    stack.document = stack.document.without_layer("p").replace_layer("grp", layers=[p])
    stack.tensors["p"] = t
    return stack


def test_per_layer_pngs_write_the_fill_and_keep_the_record():
    files, meta = layer_pngs(_stack())
    assert "p.png" in files and "masks/p.png" in files
    assert [e["pattern"] for e in meta["layers"] if e["id"] == "p"] == [
        {"scale": 150.0, "phase": [1, 2], "align": False}
    ]


def test_psd_and_ora_hold_the_pixels_with_one_warning(tmp_path):
    psd_tools = pytest.importorskip("psd_tools")
    from lasagna.export.psd import export_psd

    stack = _stack()
    ours = render_stack(stack, dtype=torch.float64).image.numpy().transpose(1, 2, 0)
    for name, export in (("s.psd", export_psd), ("s.ora", export_ora)):
        warnings: list[str] = []
        export(stack, tmp_path / name, warn=warnings.append)
        fills = [w for w in warnings if "pattern" in w]
        assert len(fills) == 1 and "live pattern fill is not written" in fills[0]
    flat = psd_tools.PSDImage.open(tmp_path / "s.psd").composite(force=True).convert("RGB")
    assert np.abs(np.asarray(flat, dtype=np.float64) - np.rint(ours * 255)).max() <= 2
