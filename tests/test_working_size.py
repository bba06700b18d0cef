"""Learned layers made at the preset's working size and enlarged to the image (lasagna.learned, preset
``working_size``): against an independent pipeline (Pillow's reduction, numpy bilinear enlargement)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from lasagna.cli import main
from lasagna.editing import edit
from tests.compose.test_resample import _bilinear_ref
from tests.support.tinylayers import ROOT, tiny_variant

PHOTO = ROOT / "examples" / "photos" / "coffee.png"  # 96×96
SIDE = 16


def _forget_pixels(out: Path) -> tuple[Path, bytes]:
    """Remove the learned layer's PNG and its ``source``, as a hand-written document would have it."""
    doc = json.loads((out / "stack.json").read_text(encoding="utf-8"))
    png = out / doc["layers"][-1]["source"]
    made = png.read_bytes()
    png.unlink()
    doc["layers"][-1]["source"] = None
    (out / "stack.json").write_text(json.dumps(doc), encoding="utf-8")
    return png, made


def _set_working(folder: Path, side: int | None) -> None:
    path = folder / "shading" / "preset.json"
    data = json.loads(path.read_text(encoding="utf-8"))
    data["working_size"] = side
    path.write_text(json.dumps(data), encoding="utf-8")


@pytest.fixture()
def catalogue(tiny, tmp_path, monkeypatch) -> Path:
    """A copy of the tiny catalogue per test: its shading preset at working size ``SIDE``, which tests change."""
    folder = tiny_variant(tiny, tmp_path / "layers")
    _set_working(folder, SIDE)
    monkeypatch.setenv("LASAGNA_LAYERS", str(folder))
    return folder


def test_amortised_layer_is_made_at_the_working_size(catalogue):
    from lasagna.generators.unet import LayerGenerator

    res = edit(PHOTO, "shading", "left")
    assert res.layer.shape == (1, 96, 96) and res.settings["working_size"] == SIDE
    with Image.open(PHOTO) as im:
        rgb = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
    small = np.stack(
        [
            np.asarray(Image.fromarray(rgb[..., c], mode="F").resize((SIDE, SIDE), Image.Resampling.BILINEAR))
            for c in range(3)
        ]
    )
    with torch.no_grad():
        y = LayerGenerator.from_pretrained(catalogue / "shading" / "generator")(torch.from_numpy(small)[None], ["left"])
    ref = _bilinear_ref(y[0, 0].double().numpy(), 96, 96)
    np.testing.assert_allclose(res.layer[0].numpy(), ref, atol=2e-5)
    # Smooth by construction: no detail finer than the working size (the base's texture cannot enter).
    assert np.abs(np.diff(res.layer[0].numpy(), axis=1)).max() <= np.abs(np.diff(y[0, 0].numpy(), axis=1)).max() + 1e-6


def test_per_image_layer_too(catalogue):
    res = edit(PHOTO, "shading", "top", generator="free", optimize=2)
    assert res.layer.shape == (1, 96, 96) and res.settings["working_size"] == SIDE
    assert res.settings["distill"]["steps"] == 2


def test_render_reproduces_and_old_layers_stay_full_size(catalogue, tmp_path, capsys):
    out = tmp_path / "w"
    assert main(["edit", str(PHOTO), "--condition", "left", "-o", str(out)]) == 0
    layer_png, made = _forget_pixels(out)
    assert main(["render", str(out)]) == 0 and layer_png.read_bytes() == made
    # A layer recorded without a working size was made at full size: it re-renders so, whatever the preset says now.
    _set_working(catalogue, None)
    full = tmp_path / "full"
    assert main(["edit", str(PHOTO), "--condition", "left", "-o", str(full)]) == 0
    doc = json.loads((full / "stack.json").read_text(encoding="utf-8"))
    assert "working_size" not in doc["layers"][-1]["settings"]
    png, made_full = _forget_pixels(full)
    _set_working(catalogue, SIDE)
    assert main(["render", str(full)]) == 0 and png.read_bytes() == made_full
    capsys.readouterr()


def test_bad_stored_working_size_is_one_line(catalogue, tmp_path, capsys):
    out = tmp_path / "w"
    assert main(["edit", str(PHOTO), "--condition", "left", "-o", str(out)]) == 0
    doc = json.loads((out / "stack.json").read_text(encoding="utf-8"))
    doc["layers"][-1]["settings"]["working_size"] = 3
    doc["layers"][-1]["source"] = None
    (out / "stack.json").write_text(json.dumps(doc), encoding="utf-8")
    capsys.readouterr()
    assert main(["render", str(out)]) == 2
    err = capsys.readouterr().err
    assert "settings.working_size" in err and "8" in err and len(err.strip().splitlines()) == 1
    shutil.rmtree(out)
