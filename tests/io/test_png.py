"""PNG reading and writing: every mode and depth against files written independently by Pillow and
pypng, hostile files (bombs, truncation, corruption, non-PNG), and atomic writes."""

from __future__ import annotations

import io
import zlib

import numpy as np
import png as pypng
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from lasagna.errors import ImageError
from lasagna.io.png import decode_png, encode_png, read_png, read_png_header, write_png
from tests import pngcraft

RNG = np.random.default_rng(7)
H, W = 13, 17


def _codes(shape, top):
    return RNG.integers(0, top + 1, size=shape)


def _stacked(img):
    planes = [img.color] + ([img.alpha] if img.alpha is not None else [])
    return np.concatenate(planes).transpose(1, 2, 0)  # (h, w, planes)


# ---- reading files written by Pillow (8-bit and lower, and 16-bit gray) ----------------------------------


@pytest.mark.parametrize("mode,planes", [("L", 1), ("LA", 2), ("RGB", 3), ("RGBA", 4)])
def test_read_pillow_8bit(tmp_path, mode, planes):
    q = _codes((H, W, planes), 255).astype(np.uint8)
    Image.fromarray(q[:, :, 0] if planes == 1 else q).save(tmp_path / "a.png")
    img = read_png(tmp_path / "a.png")
    assert img.color.dtype == np.float32 and img.color.shape == ((1 if planes < 3 else 3), H, W)
    assert (img.alpha is not None) == (planes in (2, 4))
    np.testing.assert_allclose(_stacked(img), q / 255.0, atol=1e-7)


def test_read_pillow_16bit_gray(tmp_path):
    q = _codes((H, W), 65535).astype(np.uint16)
    Image.fromarray(q).save(tmp_path / "g16.png")  # Pillow writes I;16 as a 16-bit gray PNG
    assert read_png_header(tmp_path / "g16.png").bit_depth == 16
    img = read_png(tmp_path / "g16.png")
    np.testing.assert_allclose(img.color[0], q / 65535.0, atol=1e-7)
    assert img.alpha is None


def test_read_palette_with_and_without_transparency(tmp_path):
    q = _codes((H, W), 3).astype(np.uint8)
    im = Image.new("P", (W, H))
    im.putdata(q.reshape(-1).tolist())
    pal = [10, 20, 30, 200, 100, 0, 0, 0, 255, 255, 255, 255]
    im.putpalette(pal)
    im.save(tmp_path / "p.png")
    img = read_png(tmp_path / "p.png")
    expect = np.asarray(pal, dtype=np.float64).reshape(4, 3)[q] / 255.0
    np.testing.assert_allclose(img.color.transpose(1, 2, 0), expect, atol=1e-7)
    assert img.alpha is None
    im.save(tmp_path / "pt.png", transparency=bytes([255, 0, 128, 255]))
    img = read_png(tmp_path / "pt.png")
    np.testing.assert_allclose(img.alpha[0], np.array([1.0, 0.0, 128 / 255, 1.0])[q], atol=1e-7)


def test_read_1bit(tmp_path):
    q = _codes((H, W), 1).astype(bool)
    Image.fromarray(q).save(tmp_path / "b.png")
    img = read_png(tmp_path / "b.png")
    np.testing.assert_array_equal(img.color[0], q.astype(np.float32))


# ---- reading files written by pypng (16-bit colour, low depths, interlaced) -------------------------------


@pytest.mark.parametrize("greyscale,alpha", [(True, False), (True, True), (False, False), (False, True)])
@pytest.mark.parametrize("depth", [8, 16])
@pytest.mark.parametrize("interlace", [False, True])
def test_read_pypng(tmp_path, greyscale, alpha, depth, interlace):
    planes = (1 if greyscale else 3) + alpha
    top = 2**depth - 1
    q = _codes((H, W * planes), top)
    with open(tmp_path / "a.png", "wb") as fh:
        pypng.Writer(W, H, greyscale=greyscale, alpha=alpha, bitdepth=depth, interlace=interlace).write(fh, q.tolist())
    img = read_png(tmp_path / "a.png")
    assert img.header.bit_depth == depth and img.header.interlaced == interlace
    np.testing.assert_allclose(_stacked(img), q.reshape(H, W, planes) / top, atol=1e-7)


@pytest.mark.parametrize("depth", [1, 2, 4])
def test_read_low_depth_gray(tmp_path, depth):
    top = 2**depth - 1
    q = _codes((H, W), top)
    with open(tmp_path / "a.png", "wb") as fh:
        pypng.Writer(W, H, greyscale=True, bitdepth=depth).write(fh, q.tolist())
    img = read_png(tmp_path / "a.png")
    np.testing.assert_allclose(img.color[0], q / top, atol=1e-7)


def test_16bit_gray_with_trns_becomes_alpha(tmp_path):
    q = _codes((H, W), 65535)
    q[0, 0] = 1234
    with open(tmp_path / "t.png", "wb") as fh:
        pypng.Writer(W, H, greyscale=True, bitdepth=16, transparent=1234).write(fh, q.tolist())
    img = read_png(tmp_path / "t.png")
    assert img.alpha is not None and img.alpha[0, 0, 0] == 0.0 and img.alpha.mean() > 0.9


# ---- writing, read back independently -----------------------------------------------------------------


@pytest.mark.parametrize("channels,alpha", [(1, False), (1, True), (3, False), (3, True)])
@pytest.mark.parametrize("depth", [8, 16])
def test_write_read_back_with_pypng(channels, alpha, depth):
    v = RNG.random((channels + alpha, H, W))
    data = encode_png(v[:channels], v[channels:] if alpha else None, bit_depth=depth)
    _, _, rows, info = pypng.Reader(bytes=data).read()
    assert info["bitdepth"] == depth and info["alpha"] == alpha and info["greyscale"] == (channels == 1)
    got = np.array([list(r) for r in rows]).reshape(H, W, channels + alpha)
    np.testing.assert_array_equal(got, np.rint(v.transpose(1, 2, 0) * (2**depth - 1)))


def test_write_8bit_read_back_with_pillow(tmp_path):
    v = RNG.random((3, H, W))
    write_png(tmp_path / "x.png", v)
    with Image.open(tmp_path / "x.png") as im:
        assert im.mode == "RGB"
        np.testing.assert_array_equal(np.asarray(im), np.rint(v.transpose(1, 2, 0) * 255))


@settings(max_examples=25, deadline=None)
@given(
    channels=st.sampled_from([1, 3]),
    alpha=st.booleans(),
    depth=st.sampled_from([8, 16]),
    h=st.integers(1, 9),
    w=st.integers(1, 9),
    seed=st.integers(0, 2**16),
)
def test_roundtrip_property(channels, alpha, depth, h, w, seed):
    """decode(encode(v)) is v quantised to the nearest code: error ≤ half a step."""
    v = np.random.default_rng(seed).random((channels + alpha, h, w))
    img = decode_png(encode_png(v[:channels], v[channels:] if alpha else None, bit_depth=depth), "mem")
    assert np.abs(_stacked(img) - v.transpose(1, 2, 0)).max() <= 0.5 / (2**depth - 1) + 1e-7


def test_torch_input_and_2d_gray():
    torch = pytest.importorskip("torch")
    img = decode_png(encode_png(torch.full((5, 4), 0.5)), "mem")
    assert img.color.shape == (1, 5, 4) and np.allclose(img.color, 128 / 255)


# ---- exceptions -------------------------------------------------------------------------------------------


def test_write_refuses_nan_and_out_of_range_and_leaves_file(tmp_path):
    target = tmp_path / "keep.png"
    target.write_bytes(b"original")
    with pytest.raises(ImageError, match="NaN"):
        write_png(target, np.full((1, 2, 2), np.nan))
    with pytest.raises(ImageError, match=r"values span \[-0.5, 1.5\].*clip=True"):
        write_png(target, np.array([[[-0.5, 1.5]]]))
    assert target.read_bytes() == b"original"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.png"]  # no temporary left behind
    write_png(target, np.array([[[-0.5, 1.5]]]), clip=True)
    assert read_png(target).color.tolist() == [[[0.0, 1.0]]]


@pytest.mark.parametrize("shape", [(2, 3, 3), (3,), (4, 1, 1, 1)])
def test_write_refuses_bad_shapes(shape):
    with pytest.raises(ImageError, match="expected"):
        encode_png(np.zeros(shape))


def _one_line(err: ImageError, path) -> str:
    text = str(err)
    assert "\n" not in text and text.startswith(str(path)) and "expected" in text
    return text


@pytest.mark.parametrize(
    "name,data,pattern",
    [
        ("empty", b"", "empty file"),
        ("jpeg", b"\xff\xd8\xff\xe0" + b"\x00" * 64, "not a PNG"),
        ("text", b"hello, I am not a picture at all, really not" * 2, "not a PNG"),
        ("short", b"\x89PNG\r\n\x1a\n\x00\x00", "truncated"),
    ],
)
def test_not_png(tmp_path, name, data, pattern):
    (tmp_path / name).write_bytes(data)
    with pytest.raises(ImageError, match=pattern) as info:
        read_png(tmp_path / name)
    _one_line(info.value, tmp_path / name)


def test_truncated_and_corrupt(tmp_path):
    buf = io.BytesIO()
    Image.fromarray(_codes((64, 64, 3), 255).astype(np.uint8)).save(buf, format="PNG")
    data = buf.getvalue()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageError, match="truncated"):
        read_png(tmp_path / "cut.png")
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0xFF
    (tmp_path / "flip.png").write_bytes(bytes(flipped))
    with pytest.raises(ImageError, match="CRC mismatch"):
        read_png(tmp_path / "flip.png")
    # Correct CRC around garbage deflate data.
    bad = pngcraft.png_bytes(4, 4, b"\x78\x9c" + b"\xff" * 20)
    with pytest.raises(ImageError, match="corrupt image data|truncated image data"):
        decode_png(bad, "bad")


def test_header_bomb_refused_before_decoding(tmp_path):
    (tmp_path / "bomb.png").write_bytes(pngcraft.header_bomb())
    with pytest.raises(ImageError, match="over the limit of 268435456") as info:
        read_png(tmp_path / "bomb.png")
    _one_line(info.value, tmp_path / "bomb.png")
    # Under the pixel limit, a tiny IDAT still cannot hold 10000² pixels: refused unread.
    with pytest.raises(ImageError, match="cannot expand"):
        decode_png(pngcraft.header_bomb(10_000, 10_000), "b")
    with pytest.raises(ImageError, match="over the limit of 100"):
        decode_png(pngcraft.gray8(11, 10), "small", max_pixels=100)
    with pytest.raises(ImageError, match="at most 8"):
        decode_png(pngcraft.gray8(9, 2), "side", max_side=8)


def test_idat_bomb_refused_in_bounded_memory():
    data = pngcraft.idat_bomb(expands_to=64 * 2**20)
    assert len(data) < 100_000
    with pytest.raises(ImageError, match="expands beyond"):
        decode_png(data, "zipbomb")


def test_bad_crc_in_ancillary_chunk_and_missing_iend():
    good = pngcraft.gray8(3, 3)
    bad = good[:33] + pngcraft.chunk(b"tEXt", b"a\x00b", bad_crc=True) + good[33:]
    with pytest.raises(ImageError, match="CRC mismatch in chunk 'tEXt'"):
        decode_png(bad, "x")
    with pytest.raises(ImageError, match="no IEND"):
        decode_png(good[:-12], "x")
    assert decode_png(good, "x").color.max() == pytest.approx(128 / 255)


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(ImageError, match="cannot read file") as info:
        read_png(tmp_path / "nope.png")
    _one_line(info.value, tmp_path / "nope.png")
    with pytest.raises(ImageError, match="is a folder"):
        read_png(tmp_path)


def test_raw_bytes_interlaced_matches_pypng(tmp_path):
    """The inflated size we demand of an interlaced image is what a real encoder produces."""
    for w, h in [(1, 1), (3, 7), (9, 2), (17, 13)]:
        with open(tmp_path / "i.png", "wb") as fh:
            pypng.Writer(w, h, greyscale=False, bitdepth=8, interlace=True).write(fh, _codes((h, 3 * w), 255).tolist())
        data = (tmp_path / "i.png").read_bytes()
        header = read_png_header(tmp_path / "i.png")
        idat = b"".join(_chunks(data, b"IDAT"))
        assert len(zlib.decompress(idat)) == header.raw_bytes()


def _chunks(data: bytes, kind: bytes):
    pos = 8
    while pos < len(data):
        n = int.from_bytes(data[pos : pos + 4], "big")
        if data[pos + 4 : pos + 8] == kind:
            yield data[pos + 8 : pos + 8 + n]
        pos += 12 + n
