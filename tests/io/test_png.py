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
from tests.support import pngcraft

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
    # Under the pixel limit, a few-byte IDAT still cannot hold 10000² pixels: refused unread.
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


# ---- hostile input (#16): verify without decoding, decode cost, lean decoders, banded encoding --------


def _filtered_png(filter_byte: int, width: int = 6, height: int = 4) -> bytes:
    """An 8-bit gray PNG, rows all filter 0 except the first, whose filter type byte is ``filter_byte``."""
    raw = b"".join(bytes([filter_byte if y == 0 else 0]) + bytes(range(width)) for y in range(height))
    return pngcraft.png_bytes(width, height, zlib.compress(raw))


def test_verify_png_passes_a_good_file_and_refuses_a_bad_filter_type(tmp_path):
    from lasagna.io.png import verify_png

    good = tmp_path / "good.png"
    good.write_bytes(_filtered_png(0))
    header = verify_png(good)
    assert (header.width, header.height, header.bit_depth, header.kind) == (6, 4, 8, "gray")
    bad = tmp_path / "bad.png"
    bad.write_bytes(_filtered_png(7))
    with pytest.raises(ImageError) as info:
        verify_png(bad)
    assert "row 0 has filter type 7; expected 0 to 4" in _one_line(info.value, bad)
    # a later row: the scan follows rows across inflated pieces
    raw = b"".join(bytes([9 if y == 3 else 2]) + bytes(6) for y in range(4))
    bad.write_bytes(pngcraft.png_bytes(6, 4, zlib.compress(raw)))
    with pytest.raises(ImageError, match="row 3 has filter type 9"):
        verify_png(bad)


def test_verify_png_checks_what_decoding_checks(tmp_path):
    from lasagna.io.png import verify_png

    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(pngcraft.header_bomb())
    with pytest.raises(ImageError, match="over the limit"):
        verify_png(bomb)
    with pytest.raises(ImageError, match="over the limit of 10"):
        verify_png(tmp_path / "bomb.png", max_pixels=10)
    truncated = tmp_path / "t.png"
    truncated.write_bytes(pngcraft.gray8(8, 8)[:-20])
    with pytest.raises(ImageError):
        verify_png(truncated)


def test_verify_png_does_not_decode(tmp_path, monkeypatch):
    import lasagna.io.png as png_module

    path = tmp_path / "x.png"
    Image.fromarray(_codes((H, W, 3), 255).astype(np.uint8)).save(path)

    def no_decode(*args, **kwargs):
        raise AssertionError("decoded")

    monkeypatch.setattr(png_module, "_decode_pillow", no_decode)
    monkeypatch.setattr(png_module, "_decode_pypng", no_decode)
    assert png_module.verify_png(path).pixels == H * W


def test_decode_bytes_and_file_limit():
    from lasagna.io.png import PngHeader, decode_bytes, png_file_limit

    rgb8 = PngHeader(100, 50, 8, 2, False)
    assert decode_bytes(rgb8) == (100 * 50 * 4 * 4, 100 * 50 * 8)  # RGB(+tRNS alpha) float32; Pillow codes
    gray16 = PngHeader(100, 50, 16, 0, False)
    assert decode_bytes(gray16) == (100 * 50 * 2 * 4, 0)  # pypng: rows one at a time
    rgba16 = PngHeader(10, 10, 16, 6, False)
    assert decode_bytes(rgba16)[0] == 10 * 10 * 4 * 4
    assert png_file_limit(rgb8) >= 2 * rgb8.raw_bytes()
    assert png_file_limit(rgb8) < png_file_limit(PngHeader(200, 50, 8, 2, False))


def test_a_file_far_larger_than_its_header_is_refused(tmp_path):
    from lasagna.io.png import PngHeader, png_file_limit

    data = pngcraft.gray8(4, 4)
    path = tmp_path / "padded.png"
    limit = png_file_limit(PngHeader(4, 4, 8, 0, False))
    path.write_bytes(data + b"\0" * limit)
    with pytest.raises(ImageError, match="far more than a 4x4 PNG holds"):
        read_png(path)


@pytest.mark.parametrize("mode", ["L", "LA", "RGB", "RGBA", "P"])
def test_pillow_decoder_is_bit_identical_to_the_old_formula(tmp_path, mode):
    path = tmp_path / f"{mode}.png"
    planes = {"L": 1, "LA": 2, "RGB": 3, "RGBA": 4, "P": 1}[mode]
    codes = _codes((H, W, planes), 255).astype(np.uint8)
    im = Image.fromarray(codes[:, :, 0] if planes == 1 else codes, mode="L" if mode == "P" else mode)
    if mode == "P":
        im = Image.fromarray(codes[:, :, 0], mode="P")
        im.putpalette(list(RNG.integers(0, 256, 768)))
        im.save(path, transparency=bytes(RNG.integers(0, 256, 256).astype(np.uint8)))
    else:
        im.save(path)
    ours = _stacked(read_png(path))
    with Image.open(path) as ref:
        target = {"P": "RGBA"}.get(mode, mode)
        old = np.asarray(ref.convert(target), dtype=np.float32) / 255.0
    old = old.reshape(H, W, -1)
    assert ours.dtype == np.float32 and ours.shape == old.shape
    assert np.array_equal(ours, old)


@pytest.mark.parametrize("greyscale, alpha", [(True, False), (True, True), (False, False), (False, True)])
def test_16bit_decoder_is_bit_identical_to_codes_over_65535(tmp_path, greyscale, alpha):
    planes = (1 if greyscale else 3) + alpha
    codes = _codes((H, W * planes), 65535)
    path = tmp_path / "x.png"
    with open(path, "wb") as fh:
        pypng.Writer(W, H, greyscale=greyscale, alpha=alpha, bitdepth=16).write(fh, codes.tolist())
    ours = _stacked(read_png(path))
    w, h, rows, _ = pypng.Reader(filename=str(path)).asDirect()
    ref = np.vstack([np.asarray(r, dtype=np.uint16) for r in rows]).reshape(H, W, planes)
    assert np.array_equal(ours, ref.astype(np.float32) / np.float32(65535.0))


def _bands(codes: np.ndarray, sizes):
    y = 0
    for n in sizes:
        if y >= codes.shape[0]:
            return
        yield codes[y : y + n]
        y += n


@pytest.mark.parametrize(
    "h, w, sizes",
    [(1, 1, [1]), (5, 7, [2, 2, 1]), (5, 7, [64]), (67, 130, [64, 3]), (67, 130, [10] * 7), (67, 130, [1] * 67)],
)
def test_encode_rgb8_bands_decodes_to_its_input(h, w, sizes):
    from lasagna.io.png import encode_rgb8_bands

    codes = RNG.integers(0, 256, (h, w, 3)).astype(np.uint8)
    codes[: h // 2, : w // 2] = 200  # flat areas too, where the filters differ from noise
    data = encode_rgb8_bands(_bands(codes, sizes), w, h)
    with Image.open(io.BytesIO(data)) as im:
        assert im.mode == "RGB" and im.size == (w, h)
        assert np.array_equal(np.asarray(im), codes)
    assert np.array_equal(_stacked(decode_png(data, "x")), codes.astype(np.float32) / np.float32(255.0))


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
@pytest.mark.parametrize("depth", [8, 16])
def test_encode_bands_of_every_kind_and_depth_read_back_by_pypng(channels, depth):
    """Gray, gray + alpha, RGB and RGBA at 8 and 16 bits, bands of uneven height: pypng (an independent decoder,
    exact at 16 bits) reads back the codes given."""
    import png as pypng

    from lasagna.io.png import encode_bands

    h, w = 37, 23
    top = 2**depth - 1
    codes = RNG.integers(0, top + 1, (h, w, channels)).astype(np.uint16 if depth == 16 else np.uint8)
    codes[:10, :8] = top // 3  # a flat patch
    data = encode_bands(_bands(codes, [5, 16, 7, 9]), w, h, bit_depth=depth)
    width, height, rows, info = pypng.Reader(bytes=data).read()
    assert (width, height, info["bitdepth"], info["planes"]) == (w, h, depth, channels)
    got = np.vstack([np.asarray(row, dtype=np.int64) for row in rows]).reshape(h, w, channels)
    assert np.array_equal(got, codes.astype(np.int64))


def test_encode_rgb8_bands_refuses_a_short_image():
    from lasagna.io.png import encode_rgb8_bands

    with pytest.raises(ImageError, match="got 4 rows; expected 5"):
        encode_rgb8_bands([np.zeros((4, 3, 3), np.uint8)], 3, 5)


def test_write_composite_rounds_like_composite_codes(tmp_path):
    import torch

    from lasagna.io.render import composite_codes, write_composite

    k = np.arange(256, dtype=np.float64)
    halves = (k[:255] + 0.5) / 255.0  # exactly between two codes, up to float64's rounding
    values = np.concatenate([halves, k / 255.0, [-0.5, 1.5, 1.0 + 1e-12]])
    n = values.size
    image = torch.from_numpy(np.stack([values, values[::-1], np.roll(values, 7)])).reshape(3, 1, n)
    image = image.expand(3, 3, n).contiguous()
    write_composite(image, tmp_path / "c.png")
    with Image.open(tmp_path / "c.png") as im:
        written = np.asarray(im).transpose(2, 0, 1)
    assert np.array_equal(written, composite_codes(image).numpy())
    assert np.array_equal(written, np.round(np.clip(image.numpy(), 0.0, 1.0) * 255.0).astype(np.uint8))
