"""The input policy for image files (``lasagna edit IMAGE``, ``Stack`` from a path): which formats are read,
and how, in one place.

Read: PNG (``lasagna.io.png``: 8/16-bit, bomb guards before decoding), JPEG (and MPO, the JPEG that
phones write), WebP, BMP and TIFF. TIFF is read at its depth: 8-bit by Pillow, 16-bit gray by Pillow
(exact), 16-bit RGB(A) and float by ``tifffile`` (Pillow keeps only the high byte of 16-bit RGB and
reads float colour not at all); float values must lie in [0, 1] (a linear HDR TIFF is refused, not
clipped). A tagged image (an ICC profile: JPEG's APP2, PNG's iCCP, TIFF's InterColorProfile) is converted to
sRGB at any depth (``lasagna.io.icc``). Every other format is refused unopened: Pillow is only ever asked for
these plugins, so an EPS or PDF never reaches Ghostscript, whatever its file name says.

Before any pixel is decoded the size is checked against ``max_pixels`` and the memory budget
(``lasagna.limits``), from the header alone: width, height, samples per pixel and bytes per sample
(``decode_bytes``, the one estimate of every decode path; a PNG's is ``lasagna.io.png.decode_bytes``).
An image of more than 4 samples per pixel is refused there: nothing reads it as colour and alpha (a TIFF's
header is read by tifffile before Pillow sees the file). Values are float32 channels first, ``color``
(3, h, w) and ``alpha`` (1, h, w) or None, with the bit depth they were stored at (8 or 16) so a stack
made from them saves them losslessly.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lasagna.atomic import open_regular
from lasagna.errors import ImageError, LasagnaError
from lasagna.io.icc import ICC_INTENT, codes_to_srgb, pil_to_srgb, png_icc_profile, wide_to_srgb
from lasagna.io.png import DEFAULT_MAX_PIXELS, PNG_SIGNATURE, check_size, read_png, read_png_header
from lasagna.io.png import decode_bytes as png_decode_bytes
from lasagna.limits import check_memory, raster_bytes

# Pillow's names of the formats read through Pillow (PNG has its own reader).
PILLOW_FORMATS: tuple[str, ...] = ("JPEG", "WEBP", "BMP", "TIFF")  # JPEG also opens MPO, what phones write
READABLE = "PNG, JPEG, WebP, BMP or TIFF (8/16-bit)"

# ``lasagna edit``'s pixel limit by default: the decoders' bomb guard (``lasagna.io.png.DEFAULT_MAX_PIXELS``,
# 2^28) and no lower, so what refuses a photograph is the memory budget (``edit_bytes``), not a side. A layer
# is made at its preset's working size and only enlarged to the image's (``lasagna.compose.resample``), so an
# edit's cost grows with the pixels it decodes, composites and encodes: a 24 MP photo fits the default 8 GiB.
DEFAULT_EDIT_MAX_PIXELS = DEFAULT_MAX_PIXELS

# Peak bytes per pixel of an edit of an RGB photo (decoded, composited, written with its ORA), over what the
# process holds before: 12 MP through ``lasagna edit --layer shading`` peaked at 3.2 GB resident (its ORA
# export's float64 rasters, ``lasagna.export.rasters``), ~270 bytes a pixel; rounded up for a 4-channel input.
EDIT_BYTES_PER_PIXEL = 288

# Samples per pixel an image may have: gray, gray + alpha, RGB, RGBA (CMYK is converted to RGB).
MAX_SAMPLES = 4


@dataclass
class RasterImage:
    """A decoded image file: ``color`` (3, h, w) (a gray PNG's (1, h, w)) float32 in [0, 1], ``alpha``
    (1, h, w) or None, and the bit depth it was stored at."""

    color: np.ndarray
    alpha: np.ndarray | None
    bit_depth: int


def _refuse(where: str, what: str) -> ImageError:
    return ImageError(f"{what}; expected a {READABLE} image", where)


# Scans a JPEG may hold. Decoding costs a pass over the image per scan; a progressive JPEG has ~10 (libjpeg's
# default script) and no encoder writes more than a few dozen, while a crafted file of thousands of tiny
# scans makes a small image take minutes (the "progressive JPEG" DoS; libjpeg-turbo's djpeg -maxscans).
MAX_JPEG_SCANS = 100


def _check_jpeg_scans(path: Path, where: str) -> None:
    """Refuse a JPEG with more than ``MAX_JPEG_SCANS`` start-of-scan markers, counted in its bytes (entropy-
    coded data never holds 0xFF 0xDA: a data byte 0xFF is stuffed with 0x00)."""
    with open_regular(path, where) as fh:
        scans = fh.read().count(b"\xff\xda")
    if scans > MAX_JPEG_SCANS:
        raise ImageError(
            f"JPEG has {scans} scans; expected at most {MAX_JPEG_SCANS} (a progressive JPEG has ~10)", where
        )


def decode_bytes(w: int, h: int, samples: int, sample_bytes: int) -> int:
    """Peak bytes of decoding a ``w`` × ``h`` image of ``samples`` per pixel, ``sample_bytes`` each: the decoded
    samples (a decoder holds at least 4 a pixel, Pillow's layout) and one converted or transposed copy of them,
    their float32 values, and the (4, h, w) float32 colour and alpha returned."""
    pixels = int(w) * int(h)
    decoded = pixels * max(int(samples), 4) * max(int(sample_bytes), 1)
    return 2 * decoded + raster_bytes(w, h, samples) + raster_bytes(w, h, 4)


def edit_bytes(width: int, height: int) -> int:
    """Estimated peak bytes of ``lasagna edit`` on a ``width`` × ``height`` image (``EDIT_BYTES_PER_PIXEL``)."""
    return int(width) * int(height) * EDIT_BYTES_PER_PIXEL


def check_edit_memory(width: int, height: int, where: str) -> None:
    """Refuse, before anything is decoded, an edit of a ``width`` × ``height`` image over the memory budget."""
    check_memory(edit_bytes(width, height), f"editing a {width}x{height} image", where)


def _check_pixels(w: int, h: int, max_pixels: int, where: str, samples: int = 4, sample_bytes: int = 1) -> None:
    """Refuse, before decoding, an image too large for ``max_pixels``, of more than ``MAX_SAMPLES`` samples per
    pixel, or whose decoding (``decode_bytes``) would exceed the memory budget."""
    if w * h > max_pixels:
        raise ImageError(
            f"image is {w}x{h} = {w * h} pixels, over the limit of {max_pixels}; expected at most "
            f"{max_pixels} pixels (raise --max-pixels if this is intended)",
            where,
        )
    if not 1 <= samples <= MAX_SAMPLES:
        raise ImageError(
            f"image has {samples} samples per pixel (from its header); expected 1 to {MAX_SAMPLES} (gray, gray and "
            "alpha, RGB or RGBA)",
            where,
        )
    check_memory(decode_bytes(w, h, samples, sample_bytes), f"decoding a {w}x{h} image", where)


def _tiff_header(page) -> tuple[int, int, int, int]:
    """(width, height, samples per pixel, bytes per sample) of a tifffile page, from its tags alone: every axis
    but X and Y counts as samples (a page of several planes or a volume is as costly as that many channels)."""
    shape = dict(zip(page.axes, page.shape))
    w, h = int(shape.get("X", 1)), int(shape.get("Y", 1))
    samples = int(np.prod(page.shape, dtype=np.int64)) // max(w * h, 1)
    dtype = page.dtype
    sample_bytes = dtype.itemsize if dtype is not None else -(-int(max(np.atleast_1d(page.bitspersample))) // 8)
    return w, h, samples, sample_bytes


def _pillow_header(im) -> tuple[int, int, int, int]:
    """(width, height, bands, bytes per band) of an opened Pillow image, from its header."""
    w, h = im.size
    bands = len(im.getbands())
    sample_bytes = 4 if im.mode in ("I", "F") else (2 if im.mode.startswith("I;16") else 1)
    return w, h, bands, sample_bytes


def _as_rgb(values: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(h, w[, c]) float32 → color (3, h, w) and alpha (1, h, w) | None: gray is repeated, c = 2 or 4 has alpha."""
    if values.ndim == 2:
        values = values[:, :, None]
    c = values.shape[2]
    if c not in (1, 2, 3, 4):
        raise _refuse(where, f"image has {c} channels")
    chw = np.ascontiguousarray(values.transpose(2, 0, 1), dtype=np.float32)
    color, alpha = (chw[:-1], chw[-1:]) if c in (2, 4) else (chw, None)
    if color.shape[0] == 1:
        color = np.repeat(color, 3, axis=0)
    return color, alpha


def _unit(values: np.ndarray, where: str) -> np.ndarray:
    """Integer codes / their maximum, or float values checked to lie in [0, 1]."""
    if values.dtype == np.uint8:
        return values.astype(np.float32) / np.float32(255.0)
    if values.dtype == np.uint16:
        return values.astype(np.float32) / np.float32(65535.0)
    if values.dtype.kind == "f":
        v = values.astype(np.float32)
        if not np.isfinite(v).all() or (v.size and (v.min() < 0.0 or v.max() > 1.0)):
            lo, hi = (float(np.nanmin(v)), float(np.nanmax(v))) if np.isfinite(v).any() else (np.nan, np.nan)
            raise ImageError(
                f"float image values span [{lo:.4g}, {hi:.4g}] (or are not finite); expected values in [0, 1] "
                "(a linear HDR image needs tone mapping first)",
                where,
            )
        return v
    raise _refuse(where, f"{values.dtype} samples")


def _tiff_error(exc: Exception, where: str) -> ImageError:
    return _refuse(where, f"cannot decode this TIFF ({type(exc).__name__}: {' '.join(str(exc).split())[:120]})")


def _read_tiff_wide(path: Path, where: str, max_pixels: int) -> RasterImage:
    """A 16-bit RGB(A) or float TIFF through tifffile (first page)."""
    import tifffile

    try:
        with open_regular(path, where) as fh, tifffile.TiffFile(fh) as tif:
            page = tif.pages.first
            w, h, samples, sample_bytes = _tiff_header(page)
            _check_pixels(w, h, max_pixels, where, samples, sample_bytes)
            values = page.asarray()
            axes = page.axes
            icc_tag = page.tags.get(34675)  # InterColorProfile
            icc = bytes(icc_tag.value) if icc_tag is not None else None
    except LasagnaError:  # the size and budget refusals, as they are
        raise
    except Exception as exc:  # tifffile raises ValueError, TiffFileError, KeyError, … on files it cannot decode
        raise _tiff_error(exc, where) from None
    if axes.startswith("S"):  # planar configuration: samples first
        values = np.moveaxis(values, 0, -1)
    bit_depth = 16 if values.dtype in (np.uint16, np.float32, np.float64) else 8
    color, alpha = _as_rgb(_unit(values, where), where)
    if icc:
        color = wide_to_srgb(color, icc, where) if bit_depth == 16 else codes_to_srgb(color, icc, where)
    return RasterImage(color, alpha, bit_depth=bit_depth)


def _pillow():
    """Pillow's Image module with exactly the readable formats' plugins registered: importing a plugin
    registers it, and ``Image.open(formats=PILLOW_FORMATS)`` then tries only those (never EPS, PDF, …)."""
    from PIL import BmpImagePlugin, Image, JpegImagePlugin, TiffImagePlugin, WebPImagePlugin  # noqa: F401

    return Image


def _pillow_error(exc: Exception, where: str) -> ImageError:
    from PIL import UnidentifiedImageError

    if isinstance(exc, UnidentifiedImageError):
        return _refuse(where, "cannot decode: not an image of a format lasagna reads")
    return _refuse(where, f"cannot decode ({type(exc).__name__}: {' '.join(str(exc).split())[:120]})")


def _pillow_errors(Image) -> tuple[type[Exception], ...]:
    """What Pillow raises on a file it cannot read (UnidentifiedImageError is an OSError)."""
    return (OSError, ValueError, SyntaxError, Image.DecompressionBombError)


_TIFF_MAGIC = (b"II*\x00", b"MM\x00*")


def _is_tiff(path: Path) -> bool:
    with open_regular(path) as fh:
        return fh.read(4) in _TIFF_MAGIC


def _tiff_size(path: Path, where: str) -> tuple[int, int, int, int]:
    """(width, height, samples per pixel, bytes per sample) of a TIFF's first page from its header (tifffile;
    nothing decoded)."""
    import tifffile

    try:
        with open_regular(path, where) as fh, tifffile.TiffFile(fh) as tif:
            return _tiff_header(tif.pages.first)
    except LasagnaError:
        raise
    except Exception as exc:  # as above
        raise _tiff_error(exc, where) from None


def _read_pillow(path: Path, where: str, max_pixels: int) -> RasterImage:
    from PIL import UnidentifiedImageError

    Image = _pillow()
    try:
        with open_regular(path, where) as fh, Image.open(fh, formats=PILLOW_FORMATS) as im:
            w, h, samples, sample_bytes = _pillow_header(im)
            _check_pixels(w, h, max_pixels, where, samples, sample_bytes)
            if im.format == "JPEG":
                _check_jpeg_scans(path, where)
            if im.format == "TIFF":
                bits = tuple(im.tag_v2.get(258, (8,)))
                sample_format = tuple(im.tag_v2.get(339, (1,)))
                if max(bits) > 8 and (len(bits) > 1 or 3 in sample_format):
                    return _read_tiff_wide(path, where, max_pixels)  # Pillow would drop the low byte
                if im.mode.startswith("I;16"):
                    return RasterImage(*_as_rgb(_unit(np.asarray(im).astype(np.uint16), where), where), bit_depth=16)
                if im.mode == "F":
                    return RasterImage(*_as_rgb(_unit(np.asarray(im), where), where), bit_depth=16)
                if im.mode == "I":
                    raise _refuse(where, "a 32-bit integer TIFF")
            im = as_seen(im, where)
            has_alpha = im.mode in ("RGBA", "LA", "PA") or "transparency" in im.info
            im = im.convert("RGBA" if has_alpha else "RGB")
            codes = np.asarray(im)
    except LasagnaError:  # the size and budget refusals, as they are (a LasagnaError is a ValueError)
        raise
    except _pillow_errors(Image) as exc:
        if isinstance(exc, UnidentifiedImageError) and _is_tiff(path):
            return _read_tiff_wide(path, where, max_pixels)  # a float or other wide TIFF Pillow cannot open
        raise _pillow_error(exc, where) from None
    return RasterImage(*_as_rgb(_unit(codes, where), where), bit_depth=8)


def as_seen(im, where: str):
    """A Pillow image as a viewer shows it: its EXIF orientation applied (``ImageOps.exif_transpose``) and, when it
    carries an ICC profile, converted to sRGB (``lasagna.io.icc.pil_to_srgb``: LittleCMS through ``PIL.ImageCms``,
    intent ``ICC_INTENT``), alpha kept. Every image, read from a file or given to the API (``Stack.from_image``),
    passes through here, so a path and its opened image give the same pixels. A profile that cannot be converted (a
    broken profile, a 16-bit or float image, a colour space that is not the image's) is one warning, and the codes
    are read as sRGB."""
    from PIL import ImageOps

    im = ImageOps.exif_transpose(im)
    icc = im.info.get("icc_profile")
    return pil_to_srgb(im, icc, where) if icc else im


def _magic(p: Path, where: str) -> bytes:
    try:
        with open_regular(p, where, expected="an image file or a stack folder") as fh:
            return fh.read(8)
    except IsADirectoryError:
        raise _refuse(where, "is a folder without a stack.json") from None
    except OSError as exc:
        raise ImageError(
            f"cannot read ({exc.strerror or exc}); expected an image file or a stack folder", where
        ) from None


def probe_image_file(path: str | os.PathLike, *, max_pixels: int) -> tuple[int, int]:
    """(width, height) of an image file, its format, size and decoding memory checked from its header alone
    (nothing decoded, no torch): what ``lasagna edit`` runs before it loads anything heavy."""
    p = Path(path)
    where = str(p)
    magic = _magic(p, where)
    if magic == PNG_SIGNATURE:
        header = read_png_header(p)
        check_size(header, where, max_pixels)
        check_memory(sum(png_decode_bytes(header)), f"decoding a {header.width}x{header.height} PNG", where)
        return header.width, header.height
    from PIL import UnidentifiedImageError

    if magic[:4] in _TIFF_MAGIC:  # as read_image_file does
        w, h, samples, sample_bytes = _tiff_size(p, where)
        _check_pixels(w, h, max_pixels, where, samples, sample_bytes)
    Image = _pillow()
    try:
        with open_regular(p, where) as fh, Image.open(fh, formats=PILLOW_FORMATS) as im:
            w, h, samples, sample_bytes = _pillow_header(im)
            jpeg = im.format == "JPEG"
    except _pillow_errors(Image) as exc:
        if not (isinstance(exc, UnidentifiedImageError) and _is_tiff(p)):
            raise _pillow_error(exc, where) from None
        w, h, samples, sample_bytes = _tiff_size(p, where)  # a TIFF Pillow cannot open: tifffile's header
        jpeg = False
    _check_pixels(w, h, max_pixels, where, samples, sample_bytes)
    if jpeg:
        _check_jpeg_scans(p, where)
    return w, h


def read_image_file(path: str | os.PathLike, *, max_pixels: int) -> RasterImage:
    """Read an image file under the input policy (module docstring); every refusal is one line."""
    p = Path(path)
    where = str(p)
    magic = _magic(p, where)
    if magic == PNG_SIGNATURE:
        header = read_png_header(p)
        if header.pixels <= max_pixels:
            check_memory(sum(png_decode_bytes(header)), f"decoding a {header.width}x{header.height} PNG", where)
        png = read_png(p, max_pixels=max_pixels)  # gray stays one channel, as stored
        depth = 16 if png.header.bit_depth == 16 else 8
        icc = png_icc_profile(p, where)
        if not icc:
            return RasterImage(png.color, png.alpha, depth)
        color = wide_to_srgb(png.color, icc, where) if depth == 16 else codes_to_srgb(png.color, icc, where)
        return RasterImage(color, png.alpha, depth)
    if magic[:4] in _TIFF_MAGIC:  # tifffile's header first: Pillow would print to stderr on many samples
        w, h, samples, sample_bytes = _tiff_size(p, where)
        _check_pixels(w, h, max_pixels, where, samples, sample_bytes)
    return _read_pillow(p, where, max_pixels)


__all__ = [
    "DEFAULT_EDIT_MAX_PIXELS",
    "EDIT_BYTES_PER_PIXEL",
    "PILLOW_FORMATS",
    "ICC_INTENT",
    "READABLE",
    "RasterImage",
    "as_seen",
    "check_edit_memory",
    "decode_bytes",
    "edit_bytes",
    "probe_image_file",
    "read_image_file",
]
