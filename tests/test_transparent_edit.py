"""``lasagna edit`` of an image with alpha, and ``--depth 16``, on the tiny random catalogue
(tests/support/tinylayers.py) first in LASAGNA_LAYERS.

An RGBA input makes a transparent document (``canvas.background`` null) whose new learned layer is clipped to
the image (Photoshop's clipping mask): composite.png is RGBA with the input's alpha, and its colour is the clipping
chain's (docs/ARCHITECTURE.md, ``clip``: the layer composited onto the image by the W3C general formula, the
image's alpha kept) — the image times the stored shading where the image is opaque — checked with pypng and numpy
float64 from the files the edit wrote.
"""

from __future__ import annotations

import json

import numpy as np
import png as pypng
import pytest
from PIL import Image

from lasagna.cli import main
from tests.support.tinylayers import ROOT

PHOTO = ROOT / "examples" / "photos" / "coffee.png"


@pytest.fixture(autouse=True)
def _catalogue(tiny, monkeypatch):
    monkeypatch.setenv("LASAGNA_LAYERS", str(tiny))


def _planes(path) -> tuple[np.ndarray, int]:
    """(C, h, w) values in [0, 1] of a PNG and its bit depth, read by pypng."""
    w, h, rows, info = pypng.Reader(filename=str(path)).asDirect()
    top = 2 ** info["bitdepth"] - 1
    codes = np.vstack([np.asarray(r, dtype=np.float64) for r in rows]).reshape(h, w, info["planes"])
    return codes.transpose(2, 0, 1) / top, info["bitdepth"]


@pytest.fixture
def rgba_photo(tmp_path):
    """A 40×32 crop of the coffee photo with a radial alpha (0 in the corners, 1 in the middle)."""
    with Image.open(PHOTO) as im:
        rgb = np.asarray(im.convert("RGB").resize((40, 32)))
    yy, xx = np.mgrid[0:32, 0:40]
    r = np.hypot((yy - 15.5) / 16, (xx - 19.5) / 20)
    alpha = np.clip(np.rint((1.2 - r) * 255 * 2), 0, 255).astype(np.uint8)
    path = tmp_path / "cut.png"
    Image.fromarray(np.dstack([rgb, alpha])).save(path)
    return path, rgb / 255.0, alpha / 255.0


@pytest.mark.parametrize("depth", [8, 16])
def test_an_rgba_input_gives_a_clipped_layer_and_an_rgba_composite(tmp_path, capsys, rgba_photo, depth):
    path, rgb, alpha = rgba_photo
    out = tmp_path / "out"
    code = main(
        [str(a) for a in ("edit", path, "--layer", "shading", "--condition", "left", "-o", out, "--depth", depth)]
    )
    assert code == 0, capsys.readouterr().err
    doc = json.loads((out / "stack.json").read_text())
    assert doc["canvas"]["background"] is None
    top = doc["layers"][-1]
    assert top.get("clip") is True and top["blend"] == "multiply"
    composite, bits = _planes(out / "composite.png")
    assert bits == depth and composite.shape[0] == 4
    q = 2**depth - 1
    # Alpha: the input's (the clipped layer keeps the base's alpha).
    assert np.abs(composite[3] - alpha).max() <= 0.5 / q + 1e-9
    # Colour: the opaque multiplier y (range [lo, hi] of the stored layer) onto the image (Cb, αb) by the general
    # formula, Cr = (1 − αb)·y + αb·Cb·y, clamped; the chain keeps αb. Where the image is opaque: Cb·y.
    stored, _ = _planes(out / top["source"])
    lo, hi = top["range"]
    y = lo + (hi - lo) * stored[:1]
    ab = alpha[None]
    expected = np.clip((1.0 - ab) * y + ab * rgb.transpose(2, 0, 1) * y, 0.0, 1.0)
    seen = alpha > 0.05
    assert np.abs(composite[:3][:, seen] - expected[:, seen]).max() <= 1.5 / 255
    opaque = alpha == 1.0
    assert opaque.sum() > 100
    assert np.abs(composite[:3][:, opaque] - np.clip(rgb.transpose(2, 0, 1) * y, 0, 1)[:, opaque]).max() <= 1.5 / 255
    # The ORA carries the transparency: no background layer, an RGBA merged image.
    import zipfile

    with zipfile.ZipFile(out / "stack.ora") as zf:
        assert "data/_background.png" not in zf.namelist()
        with Image.open(zf.open("mergedimage.png")) as im:
            assert im.mode == "RGBA"


def test_an_rgb_input_stays_opaque(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["edit", str(PHOTO), "--layer", "shading", "--condition", "left", "-o", str(out), "--no-ora"]) == 0
    doc = json.loads((out / "stack.json").read_text())
    assert doc["canvas"]["background"] == [0.0, 0.0, 0.0] and "clip" not in doc["layers"][-1]
    with Image.open(out / "composite.png") as im:
        assert im.mode == "RGB"
