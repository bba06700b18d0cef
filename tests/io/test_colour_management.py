"""Photographs as viewers show them (issue 27): ICC-tagged inputs converted to sRGB (``lasagna.io.image.as_seen``)
against an independent float64 conversion, outputs tagged sRGB, EXIF orientation the same for a path and an
opened image."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from lasagna.cli import main
from lasagna.io.image import read_image_file
from lasagna.io.png import read_png
from lasagna.io.stack import Stack
from tests.support.icc import display_p3_profile, p3_to_srgb_codes


def _photo(h: int = 48, w: int = 64) -> np.ndarray:
    rng = np.random.default_rng(7)
    codes = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    codes[:4, :4] = (250, 120, 30)  # saturated orange: a P3 colour sRGB codes misread by a visible margin
    return codes


def _codes(color: np.ndarray) -> np.ndarray:
    return np.rint(color.transpose(1, 2, 0) * 255.0).astype(int)


@pytest.mark.parametrize("fmt", ["TIFF", "WEBP"])
def test_display_p3_is_converted_to_srgb(tmp_path, fmt):
    codes = _photo()
    path = tmp_path / f"p3.{fmt.lower()}"
    kwargs = {"lossless": True} if fmt == "WEBP" else {}
    Image.fromarray(codes).save(path, format=fmt, icc_profile=display_p3_profile(), **kwargs)
    ours = _codes(read_image_file(path, max_pixels=10**6).color)
    ref = p3_to_srgb_codes(codes).astype(int)
    assert np.abs(ours - ref).max() <= 2
    assert np.abs(codes.astype(int) - ref).max() > 10  # read as sRGB codes, it would be far off


def test_display_p3_jpeg_through_edit(tmp_path, capsys):
    path = tmp_path / "p3.jpg"
    Image.fromarray(_photo()).save(path, quality=95, icc_profile=display_p3_profile())
    with Image.open(path) as im:  # the JPEG's decoded P3 codes, converted independently
        ref = p3_to_srgb_codes(np.asarray(im.convert("RGB"))).astype(int)
    out = tmp_path / "out"
    assert main(["edit", str(path), "--condition", "left", "--steps", "1", "--no-ora", "-o", str(out)]) == 0
    base = read_png(out / "layers" / "base.png").color
    assert np.abs(_codes(base) - ref).max() <= 2
    with Image.open(out / "composite.png") as im:
        assert im.info.get("srgb") == 0  # the composite says it is sRGB (perceptual)


def test_composite_png_is_tagged_srgb(tmp_path, capsys):
    out = tmp_path / "c.png"
    basic = Path(__file__).resolve().parents[2] / "examples" / "stacks" / "basic"
    assert main(["composite", str(basic), "-o", str(out)]) == 0
    with Image.open(out) as im:
        assert im.info.get("srgb") == 0


def test_unreadable_profile_is_one_warning(tmp_path, capsys):
    codes = _photo(8, 8)
    path = tmp_path / "broken.tiff"
    Image.fromarray(codes).save(path, icc_profile=b"not an ICC profile at all" * 8)
    with pytest.warns(UserWarning, match=r"broken.tiff: cannot read its ICC profile .*; read as sRGB"):
        img = read_image_file(path, max_pixels=10**6)
    assert np.array_equal(_codes(img.color), codes)  # read as sRGB codes, unchanged


def test_pil_image_is_converted_as_a_path_is(tmp_path):
    codes = _photo(16, 16)
    buf = io.BytesIO()
    Image.fromarray(codes).save(buf, format="TIFF", icc_profile=display_p3_profile())
    path = tmp_path / "p3.tiff"
    path.write_bytes(buf.getvalue())
    from_path = read_image_file(path, max_pixels=10**6).color
    with Image.open(path) as im:
        from_image = Stack.from_image(im).tensors["base"].color
    assert torch.equal(from_image, torch.from_numpy(from_path))


def _oriented_jpeg(path, orientation: int) -> np.ndarray:
    codes = np.zeros((20, 30, 3), np.uint8)
    codes[:10, :15] = 255  # a white top-left quarter: where it ends up shows the rotation
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(codes).save(path, quality=95, exif=exif)
    return codes


@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_exif_orientation_is_the_same_for_a_path_and_an_image(tmp_path, orientation):
    from lasagna.editing import input_stack  # what lasagna.edit reads, a path or an image

    path = tmp_path / "turned.jpg"
    _oriented_jpeg(path, orientation)
    from_path = read_image_file(path, max_pixels=10**6).color
    assert from_path.shape[1:] == ((30, 20) if orientation in (6, 8) else (20, 30))
    with Image.open(path) as im:
        stack = Stack.from_image(im)
        assert torch.equal(stack.tensors["base"].color, torch.from_numpy(from_path))
        edited_image = input_stack(im).tensors["base"].color
    assert torch.equal(edited_image, input_stack(path).tensors["base"].color)
