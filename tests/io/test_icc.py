"""Tagged inputs converted to sRGB (``lasagna.io.icc``), against LittleCMS through Pillow's ImageCms.

Pillow cannot build a Display P3 profile (``ImageCms.createProfile`` makes sRGB, LAB and XYZ only), so
``display_p3()`` writes one: an ICC v2 matrix-shaper with Display P3's D50-adapted colorants (as Apple's profile
holds them) and the sRGB tone curve as a ``para`` curve (ICC.1:2010 section 10.18, function type 3).
"""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
from PIL import Image, ImageCms

from lasagna.io.icc import matrix_shaper_to_srgb, png_icc_profile
from lasagna.io.image import read_image_file
from lasagna.io.png import encode_png

# Display P3 (DCI-P3 primaries, D65 white, sRGB curve) adapted to D50 by Bradford: Apple's rXYZ/gXYZ/bXYZ.
P3_COLORANTS = ((0.515102, 0.241182, -0.001050), (0.291965, 0.692236, 0.041882), (0.157153, 0.066582, 0.784378))
SRGB_PARA = (2.4, 1 / 1.055, 0.055 / 1.055, 1 / 12.92, 0.04045)


def _s15(v: float) -> bytes:
    return struct.pack(">i", round(v * 65536))


def display_p3() -> bytes:
    """An ICC v2.1 display profile, RGB → XYZ (D50): desc, wtpt, r/g/bXYZ and r/g/bTRC (``para`` type 3)."""
    desc_text = b"Display P3 (test)\0"
    desc = b"desc" + b"\0" * 4 + struct.pack(">I", len(desc_text)) + desc_text + b"\0" * 12 + b"\0" * 67
    xyz = {
        b"wtpt": (0.9642, 1.0, 0.8249),
        b"rXYZ": P3_COLORANTS[0],
        b"gXYZ": P3_COLORANTS[1],
        b"bXYZ": P3_COLORANTS[2],
    }
    para = b"para" + b"\0" * 4 + struct.pack(">HH", 3, 0) + b"".join(_s15(v) for v in SRGB_PARA)
    tags = [(b"desc", desc)] + [(k, b"XYZ " + b"\0" * 4 + b"".join(_s15(c) for c in v)) for k, v in xyz.items()]
    tags += [(b"rTRC", para), (b"gTRC", para), (b"bTRC", para)]
    offset = 128 + 4 + 12 * len(tags)
    table, data = b"", b""
    for sig, body in tags:
        body += b"\0" * (-len(body) % 4)
        table += struct.pack(">4sII", sig, offset + len(data), len(body))
        data += body
    size = offset + len(data)
    header = struct.pack(">I4sI4s4s4s", size, b"lcms", 0x02100000, b"mntr", b"RGB ", b"XYZ ") + b"\0" * 12
    header += b"acsp" + b"\0" * 24 + _s15(0.9642) + _s15(1.0) + _s15(0.8249)
    header += b"\0" * (128 - len(header))
    return header + struct.pack(">I", len(tags)) + table + data


def _pillow_srgb(codes: np.ndarray, icc: bytes) -> np.ndarray:
    """LittleCMS's sRGB codes (h, w, 3) of 8-bit ``codes`` tagged ``icc`` (the independent reference)."""
    src = ImageCms.ImageCmsProfile(io.BytesIO(icc))
    out = ImageCms.profileToProfile(
        Image.fromarray(codes), src, ImageCms.createProfile("sRGB"), renderingIntent=ImageCms.Intent.PERCEPTUAL
    )
    return np.asarray(out).astype(np.int32)


def _with_iccp(png: bytes, icc: bytes) -> bytes:
    """``png`` with an iCCP chunk inserted after IHDR (PNG spec 11.3.3.3)."""
    body = b"Display P3\0\0" + zlib.compress(icc)
    chunk = struct.pack(">I", len(body)) + b"iCCP" + body + struct.pack(">I", zlib.crc32(b"iCCP" + body))
    return png[:33] + chunk + png[33:]


@pytest.fixture(scope="module")
def p3_photo() -> np.ndarray:
    """Saturated P3 colours, gradients and grays: (24, 32, 3) 16-bit codes."""
    rng = np.random.default_rng(0)
    return rng.integers(0, 65536, (24, 32, 3), dtype=np.uint16)


def test_the_test_profile_is_display_p3_to_littlecms():
    prof = ImageCms.ImageCmsProfile(io.BytesIO(display_p3()))
    assert prof.profile.is_matrix_shaper and "Display P3" in ImageCms.getProfileDescription(prof)
    np.testing.assert_allclose(prof.profile.red_colorant[0], P3_COLORANTS[0], atol=1e-4)
    # P3's pure red is outside sRGB: LittleCMS clips it to sRGB red (255, 0, 0) or near it.
    assert _pillow_srgb(np.array([[[255, 0, 0]]], np.uint8), display_p3())[0, 0, 0] == 255


@pytest.mark.parametrize("kind", ["png8", "png16", "jpeg", "tiff16"])
def test_a_display_p3_image_reads_as_its_srgb_conversion_within_2_codes(tmp_path, p3_photo, kind):
    # The 16-bit files hold the 8-bit codes × 257 (the same colours), so LittleCMS's 8-bit conversion is their
    # reference too: what differs is only the 16-bit path's float64 maths against LittleCMS's 8-bit tables.
    icc = display_p3()
    codes8 = (p3_photo >> 8).astype(np.uint8)
    p3_photo = codes8.astype(np.uint16) * np.uint16(257)
    path = tmp_path / f"p3.{kind[:4] if kind != 'tiff16' else 'tif'}"
    if kind == "png8":
        path.write_bytes(_with_iccp(encode_png(np.moveaxis(codes8, -1, 0) / 255.0, bit_depth=8), icc))
        assert png_icc_profile(path, "p3") == icc
    elif kind == "png16":
        path.write_bytes(_with_iccp(encode_png(np.moveaxis(p3_photo, -1, 0) / 65535.0, bit_depth=16), icc))
    elif kind == "jpeg":
        Image.fromarray(codes8).save(path, quality=100, subsampling=0, icc_profile=icc)
        codes8 = np.asarray(Image.open(path))  # what the JPEG holds
    else:
        import tifffile

        tifffile.imwrite(path, p3_photo, photometric="rgb", iccprofile=icc)
    got = np.round(np.moveaxis(read_image_file(path, max_pixels=1 << 20).color, 0, -1) * 255.0).astype(np.int32)
    ref = _pillow_srgb(codes8, icc)
    assert np.abs(got - ref).max() <= 2, f"{kind}: {np.abs(got - ref).max()} codes from LittleCMS"
    untagged = codes8.astype(np.int32)
    assert np.abs(untagged - ref).max() > 10  # the profile matters on these colours


def test_matrix_shaper_in_float64_is_littlecms_at_8_bits():
    # Every 8-bit code on each axis and a random cloud: the float64 transform within 1 code of LittleCMS's own.
    rng = np.random.default_rng(1)
    codes = np.concatenate([np.repeat(np.arange(256, dtype=np.uint8)[:, None], 3, 1), rng.integers(0, 256, (768, 3))])
    codes = codes.astype(np.uint8).reshape(1, -1, 3)
    got = matrix_shaper_to_srgb(np.moveaxis(codes, -1, 0) / 255.0, display_p3())
    got = np.round(np.moveaxis(got, 0, -1) * 255.0).astype(np.int32)
    assert np.abs(got - _pillow_srgb(codes, display_p3())).max() <= 1


def test_a_table_profile_at_16_bits_is_read_as_srgb_with_a_warning(tmp_path, p3_photo):
    lab = ImageCms.ImageCmsProfile(ImageCms.createProfile("LAB")).tobytes()
    path = tmp_path / "lab.png"
    path.write_bytes(_with_iccp(encode_png(np.moveaxis(p3_photo, -1, 0) / 65535.0, bit_depth=16), lab))
    with pytest.warns(UserWarning, match="read as sRGB"):
        got = read_image_file(path, max_pixels=1 << 20).color
    np.testing.assert_array_equal(got, np.moveaxis(p3_photo, -1, 0).astype(np.float32) / np.float32(65535.0))


def _chunks(png: bytes) -> list[bytes]:
    out, i = [], 8
    while i < len(png):
        n, t = struct.unpack(">I4s", png[i : i + 8])
        out.append(t)
        i += 12 + n
    return out


def test_a_display_p3_photos_composite_is_its_srgb_conversion_tagged_srgb(tmp_path, p3_photo):
    # lasagna edit of a P3-tagged PNG, the learned layer then hidden: composite.png is LittleCMS's sRGB conversion of
    # the photo within 2 codes, and says sRGB (its sRGB chunk); no output embeds the source profile.
    import json

    from lasagna.cli import main

    codes8 = (p3_photo >> 8).astype(np.uint8)
    photo = tmp_path / "p3.png"
    photo.write_bytes(_with_iccp(encode_png(np.moveaxis(codes8, -1, 0) / 255.0, bit_depth=8), display_p3()))
    out = tmp_path / "out"
    assert main(["edit", str(photo), "--layer", "color", "--optimize", "1", "-o", str(out), "--no-ora"]) == 0
    doc = json.loads((out / "stack.json").read_text())
    doc["layers"][-1]["visible"] = False
    (out / "stack.json").write_text(json.dumps(doc))
    assert main(["composite", str(out)]) == 0
    png = (out / "composite.png").read_bytes()
    got = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int32)
    ref = _pillow_srgb(codes8, display_p3())
    assert np.abs(got - ref).max() <= 2
    assert b"sRGB" in _chunks(png) and b"iCCP" not in _chunks(png)
    assert b"iCCP" not in _chunks((out / "layers" / "base.png").read_bytes())
