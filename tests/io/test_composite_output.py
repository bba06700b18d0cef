"""composite.png as ``lasagna composite`` writes it: 8- or 16-bit (``--depth``), RGB, or RGBA for a transparent
document (``canvas.background`` null).

References are independent: ``tests/support/reference.py`` (numpy float64, reading the stack folder with pypng),
and the PNGs are read back with pypng (exact at 16 bits) and Pillow.
"""

from __future__ import annotations

import io

import numpy as np
import png as pypng
import pytest
import torch
from PIL import Image

from lasagna.cli import main
from lasagna.errors import ImageError
from lasagna.io.render import encode_composite, render_stack
from lasagna.io.stack import Stack, load_stack
from tests.support.reference import composite_reference_rgba

H, W = 19, 23


def read_codes(data: bytes) -> tuple[np.ndarray, int]:
    """(H, W, planes) int64 codes and the bit depth, as pypng reads them."""
    width, height, rows, info = pypng.Reader(bytes=data).read()
    codes = np.vstack([np.asarray(row, dtype=np.int64) for row in rows]).reshape(height, width, info["planes"])
    return codes, info["bitdepth"]


def shaded_stack(transparent: bool) -> Stack:
    """A 16-bit base (with partial alpha and a hole when ``transparent``) and a multiply layer of range [0, 2]."""
    g = torch.Generator().manual_seed(3)
    base = torch.rand(3, H, W, generator=g, dtype=torch.float64)
    alpha = None
    if transparent:
        alpha = torch.rand(1, H, W, generator=g, dtype=torch.float64)
        alpha[:, :4, :5] = 0.0  # a hole
    stack = Stack.from_image(base.float(), alpha=None if alpha is None else alpha.float(), bit_depth=16)
    shade = 0.2 + 1.6 * torch.rand(1, H - 4, W - 6, generator=g)
    stack.add_layer("shade", shade, blend="multiply", range=(0.0, 2.0), offset=(3, 2), opacity=0.8)
    return stack


class TestDepth:
    @pytest.mark.parametrize("transparent", [False, True])
    @pytest.mark.parametrize("depth", [8, 16])
    def test_the_cli_composite_matches_the_float64_reference(self, tmp_path, capsys, depth, transparent):
        folder = tmp_path / "stack"
        shaded_stack(transparent).save(folder)
        out = tmp_path / "c.png"
        assert main(["composite", str(folder), "-o", str(out), "--depth", str(depth)]) == 0
        kind = "RGBA" if transparent else "RGB"
        assert f"{kind}, {depth}-bit" in capsys.readouterr().out
        codes, bits = read_codes(out.read_bytes())
        assert bits == depth and codes.shape == (H, W, 4 if transparent else 3)
        color, alpha = composite_reference_rgba(folder)
        top = 2**depth - 1
        ref_alpha = np.rint(alpha[0] * top)
        if transparent:
            assert np.abs(codes[..., 3] - ref_alpha).max() <= 1
            # The hole stays transparent where the shade layer (offset (3, 2)) does not reach; over it, an unclipped
            # multiply paints its own colour (W3C section 10: Cr = Cs where αb = 0), with α = opacity.
            assert (codes[..., 3][:2, :5] == 0).all() and (codes[..., 3][:4, :3] == 0).all()
            assert np.abs(codes[..., 3][2:4, 3:5] - 0.8 * top).max() <= 1
        seen = alpha[0] > 1e-3  # straight colour is defined where there is alpha
        ref = np.rint(color.transpose(1, 2, 0) * top)
        assert np.abs(codes[..., :3][seen] - ref[seen]).max() <= 1

    def test_16_bits_keep_what_8_bits_round_away(self, tmp_path):
        """A smooth ramp: 16-bit codes sit within half a code of 65535·v; 8-bit ones repeat over runs of pixels."""
        ramp = torch.linspace(0.0, 1.0, 1000, dtype=torch.float64).view(1, 1, -1).expand(3, 2, -1).contiguous()
        result = render_stack(Stack.from_image(ramp.float()), dtype=torch.float64)
        codes16, _ = read_codes(encode_composite(result, depth=16))
        codes8, _ = read_codes(encode_composite(result, depth=8))
        assert np.abs(codes16[0, :, 0] - ramp[0, 0].numpy() * 65535).max() <= 0.5 + 1e-6
        assert len(np.unique(codes16[0, :, 0])) == 1000 and len(np.unique(codes8[0, :, 0])) == 256

    def test_pillow_reads_the_8_bit_rgba_composite(self, tmp_path):
        stack = shaded_stack(True)
        result = render_stack(stack)
        with Image.open(io.BytesIO(encode_composite(result))) as im:
            assert im.mode == "RGBA" and im.size == (W, H) and im.info.get("srgb") == 0
            got = np.asarray(im)
        assert np.array_equal(got[..., 3], np.rint(result.alpha[0].double().numpy() * 255).astype(np.uint8))

    def test_a_bad_depth_is_one_line_exit_2(self, tmp_path, capsys):
        folder = tmp_path / "stack"
        shaded_stack(False).save(folder)
        assert main(["composite", str(folder), "--depth", "12"]) == 2
        err = capsys.readouterr().err
        assert "--depth" in err and "Traceback" not in err and not (folder / "composite.png").exists()
        with pytest.raises(ImageError, match="expected 8 or 16"):
            encode_composite(render_stack(shaded_stack(False)), depth=12)


class TestTransparentDocument:
    def test_an_image_with_alpha_makes_a_transparent_document_that_reads_back(self, tmp_path):
        stack = shaded_stack(True)
        assert stack.document.canvas.background is None
        assert Stack.from_image(torch.rand(3, 4, 4)).document.canvas.background == (0.0, 0.0, 0.0)
        folder = tmp_path / "s"
        stack.save(folder)
        text = (folder / "stack.json").read_text()
        assert '"background": null' in text
        again = load_stack(folder)
        assert again.document == stack.document
        a, b = render_stack(stack), render_stack(again)  # the saved layers are 16-bit codes of the values
        torch.testing.assert_close(a.alpha, b.alpha, atol=4 / 65535, rtol=0)
        torch.testing.assert_close(a.image * a.alpha, b.image * b.alpha, atol=4 / 65535, rtol=0)

    def test_an_opaque_document_stays_rgb(self):
        result = render_stack(shaded_stack(False))
        assert result.alpha is None
        codes, _ = read_codes(encode_composite(result))
        assert codes.shape[2] == 3


def test_the_api_gives_a_transparent_composite_as_rgba_codes():
    """``lasagna.to_numpy`` / ``to_pil`` of a transparent document's render: the codes composite.png holds."""
    from lasagna.api import to_numpy, to_pil

    result = render_stack(shaded_stack(True))
    codes, _ = read_codes(encode_composite(result))
    got = to_numpy(result)
    assert got.shape == (H, W, 4) and np.array_equal(got.astype(np.int64), codes)
    assert to_pil(result).mode == "RGBA" and to_pil(render_stack(shaded_stack(False))).mode == "RGB"
