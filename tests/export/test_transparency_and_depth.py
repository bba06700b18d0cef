"""Transparent documents and 16-bit PSDs through the interchange formats.

* A transparent document (``canvas.background`` null) is written with no background layer: ORA and PSD layers
  and merged images carry its transparency, read back by psd-tools and by our ORA reader (and ``import-ora`` /
  ``import-psd`` give a transparent document back).
* ``encode_psd(depth=16)`` / ``lasagna export --psd --depth 16``: psd-tools reads a 16-bit file whose layers
  hold our 16-bit codes and whose merged image is within one 16-bit code of a numpy float64 composite.
* An OpenRaster file without a background layer that does not cover its canvas (as Krita and MyPaint write them)
  imports as a transparent document.
"""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
import torch
from PIL import Image

from lasagna.cli import main
from lasagna.export.ora import encode_ora
from lasagna.export.ora_import import import_ora
from lasagna.io.render import render_stack
from lasagna.io.stack import Stack, load_stack
from tests.support.reference import composite_reference_rgba

psd_tools = pytest.importorskip("psd_tools")
from psd_tools import PSDImage  # noqa: E402

from lasagna.export.psd import encode_psd  # noqa: E402
from lasagna.export.psd_import import read_psd  # noqa: E402

H, W = 17, 21


def stack_of(transparent: bool) -> Stack:
    """A base (partial alpha when ``transparent``), a screen layer and a multiply layer above 1 (a dodge pair)."""
    g = torch.Generator().manual_seed(11)
    alpha = torch.rand(1, H, W, generator=g) if transparent else None
    if alpha is not None:
        alpha[:, :, :4] = 0.0
    stack = Stack.from_image(torch.rand(3, H, W, generator=g), alpha=alpha)
    stack.add_layer("glow", torch.rand(3, 6, 7, generator=g), blend="screen", offset=(5, 4), opacity=0.7)
    shade = 0.3 + 1.5 * torch.rand(1, H, W, generator=g)
    stack.add_layer("shade", shade, blend="multiply", range=(0.0, 2.0))
    return stack


def psd_float(layer_or_psd) -> np.ndarray:
    return np.asarray(layer_or_psd.numpy(), dtype=np.float64)


class TestPsd:
    @pytest.mark.parametrize("transparent", [False, True])
    def test_16_bit_psd_reads_back_in_psd_tools(self, tmp_path, transparent):
        stack = stack_of(transparent)
        folder = tmp_path / "s"
        stack.save(folder)
        out = tmp_path / "out.psd"
        assert main(["export", str(folder), "--psd", str(out), "--depth", "16"]) == 0
        psd = PSDImage.open(out)
        assert psd.depth == 16 and (psd.width, psd.height) == (W, H)
        names = [layer.name for layer in psd.descendants()]
        assert ("Background" in names) != transparent
        # The merged image: our composite within a 16-bit code of the float64 reference (stored 16-bit layers).
        color, alpha = composite_reference_rgba(folder)
        merged = psd_float(psd)
        assert merged.shape[2] == 4
        seen = alpha[0] > 1e-3
        assert np.abs(merged[..., 3] - alpha[0]).max() <= 1.5 / 65535
        got, ref = merged[..., :3][seen], color.transpose(1, 2, 0)[seen]
        assert np.abs(got - ref).max() <= 1.5 / 65535
        # A layer holds our 16-bit codes: the base's colour where it has alpha.
        base = next(layer for layer in psd.descendants() if layer.name == "base")
        values = psd_float(base)
        ours = load_stack(folder).tensors["base"].color.double().numpy().transpose(1, 2, 0)
        keep = values[..., 3] > 0
        assert np.abs(values[..., :3][keep] - ours[keep]).max() <= 1.0 / 65535

    def test_8_bit_transparent_psd_has_no_background_and_its_alpha(self):
        stack = stack_of(True)
        result = render_stack(stack, dtype=torch.float64)
        psd = PSDImage.open(io.BytesIO(encode_psd(stack, composite=result)))
        assert psd.depth == 8 and "Background" not in [layer.name for layer in psd.descendants()]
        merged = psd_float(psd)
        assert np.abs(merged[..., 3] - result.alpha[0].numpy()).max() <= 0.5 / 255 + 1e-6

    def test_a_bad_depth_is_refused(self):
        from lasagna.errors import ExportError

        with pytest.raises(ExportError, match="expected 8 or 16"):
            encode_psd(stack_of(False), depth=32)

    def test_import_psd_of_our_transparent_export_is_transparent(self, tmp_path):
        stack = stack_of(True)
        path = tmp_path / "t.psd"
        path.write_bytes(encode_psd(stack, composite=render_stack(stack)))
        back = read_psd(path, warn=lambda m: None)
        assert back.document.canvas.background is None
        a, b = render_stack(stack, dtype=torch.float64), render_stack(back, dtype=torch.float64)
        assert np.abs(a.alpha.numpy() - b.alpha.numpy()).max() <= 1 / 255


class TestOra:
    def test_a_transparent_document_round_trips_through_openraster(self, tmp_path):
        stack = stack_of(True)
        result = render_stack(stack)
        data = encode_ora(stack, composite=result, warn=lambda m: None)
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            assert "data/_background.png" not in zf.namelist()
            with Image.open(io.BytesIO(zf.read("mergedimage.png"))) as im:
                assert im.mode == "RGBA"
                merged = np.asarray(im)
            with Image.open(io.BytesIO(zf.read("Thumbnails/thumbnail.png"))) as im:
                assert im.mode == "RGBA"
        assert np.array_equal(merged[..., 3], np.rint(result.alpha[0].double().numpy() * 255).astype(np.uint8))
        path = tmp_path / "t.ora"
        path.write_bytes(data)
        back = import_ora(path, warn=lambda m: None)
        assert back.document.canvas.background is None
        b = render_stack(back, dtype=torch.float64)
        assert np.abs(b.alpha.numpy() - result.alpha.double().numpy()).max() <= 1 / 255 + 1e-6

    def test_an_opaque_document_keeps_its_background_layer(self, tmp_path):
        stack = stack_of(False)
        with zipfile.ZipFile(io.BytesIO(encode_ora(stack, warn=lambda m: None))) as zf:
            assert "data/_background.png" in zf.namelist()
            with Image.open(io.BytesIO(zf.read("mergedimage.png"))) as im:
                assert im.mode == "RGB"

    def test_a_foreign_ora_not_covering_its_canvas_imports_transparent(self, tmp_path):
        """An OpenRaster file as a paint program writes one (no background layer of ours): a layer smaller than the
        canvas is a transparent document, its alpha the layer's; a full opaque bottom layer keeps it opaque."""

        def ora(layer: np.ndarray, x: int, y: int) -> bytes:
            buf = io.BytesIO()
            Image.fromarray(layer).save(buf, format="PNG")
            xml = (
                f'<?xml version="1.0" encoding="UTF-8"?><image w="{W}" h="{H}"><stack>'
                f'<layer name="paint" src="data/paint.png" x="{x}" y="{y}" opacity="1.0" /></stack></image>'
            )
            out = io.BytesIO()
            with zipfile.ZipFile(out, "w") as zf:
                zf.writestr("mimetype", "image/openraster", compress_type=zipfile.ZIP_STORED)
                zf.writestr("stack.xml", xml)
                zf.writestr("data/paint.png", buf.getvalue())
            return out.getvalue()

        rng = np.random.default_rng(2)
        small = rng.integers(0, 256, (5, 6, 4), dtype=np.uint8)
        path = tmp_path / "small.ora"
        path.write_bytes(ora(small, 3, 2))
        stack = import_ora(path, warn=lambda m: None)
        assert stack.document.canvas.background is None
        result = render_stack(stack, dtype=torch.float64)
        expected = np.zeros((H, W))
        expected[2:7, 3:9] = small[..., 3] / 255.0
        assert np.abs(result.alpha[0].numpy() - expected).max() <= 1e-6
        full = rng.integers(0, 256, (H, W, 4), dtype=np.uint8)
        full[..., 3] = 255
        path.write_bytes(ora(full, 0, 0))
        assert import_ora(path, warn=lambda m: None).document.canvas.background is not None
