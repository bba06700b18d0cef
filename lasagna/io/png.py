"""PNG read/write: 8- and 16-bit gray, gray+alpha, RGB, RGBA and palette images as float32 in [0, 1].

Reading is in two steps. First the file's chunk structure is checked *without decoding pixels*:
signature, IHDR first, CRCs, IEND present, the pixel count under a limit (decompression bombs are
refused from the 25-byte header), and the IDAT stream inflated in bounded pieces and counted — it
must expand to exactly the bytes the header's size needs (a "huge header, tiny IDAT" bomb and a
"tiny header, huge IDAT" bomb both fail here, in bounded memory). Only then are the pixels decoded:
by Pillow for 8-bit and lower depths (fast, C), by pypng for 16-bit (Pillow drops the low byte of
16-bit RGB(A) and gray+alpha PNGs).

Values are channels first: ``color`` (C, h, w) with C = 1 (gray) or 3 (RGB), ``alpha`` (1, h, w) or
None. A PNG stores unsigned integers q in [0, 2^d − 1]; the value is q / (2^d − 1). Writing rounds
v · (2^d − 1) to nearest; values outside [0, 1] or NaN are an error unless the caller asks to clip.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from dataclasses import dataclass
from typing import Literal

import numpy as np
import png as pypng
from PIL import Image

from lasagna.atomic import open_regular, write_output
from lasagna.errors import ImageError

# Pixels beyond which a PNG is refused before decoding. 2^28 (16384²) float32 RGBA pixels are 4 GiB:
# anything larger is not a layer a CPU session can composite, and is what decompression bombs claim.
DEFAULT_MAX_PIXELS = 2**28

# zlib's deflate expands at most ~1032:1 (a 258-byte match coded in 2 bits, RFC 1951); an IDAT stream
# shorter than needed/1032 cannot hold the image its header claims, so it is refused unread.
DEFLATE_MAX_RATIO = 1032

# A file whose size is far above what its pixels could need (twice the raw bytes plus room for ICC
# profiles, EXIF and text chunks) is not read into memory.
_ANCILLARY_SLACK = 64 * 2**20

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

# PNG colour types (PNG spec, 11.2.2) -> (name, samples per pixel, allowed bit depths).
_COLOR_TYPES: dict[int, tuple[str, int, tuple[int, ...]]] = {
    0: ("gray", 1, (1, 2, 4, 8, 16)),
    2: ("rgb", 3, (8, 16)),
    3: ("palette", 1, (1, 2, 4, 8)),
    4: ("gray+alpha", 2, (8, 16)),
    6: ("rgba", 4, (8, 16)),
}

# Adam7 passes: (x0, y0, dx, dy) (PNG spec, 8.2).
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2))

_EXPECTED_PNG = "expected a complete PNG (8/16-bit gray, gray+alpha, RGB, RGBA or palette)"

BitDepth = Literal[8, 16]


@dataclass(frozen=True)
class PngHeader:
    """The IHDR of a PNG: what the file claims before any pixel is decoded."""

    width: int
    height: int
    bit_depth: int
    color_type: int
    interlaced: bool

    @property
    def kind(self) -> str:
        """``gray``, ``gray+alpha``, ``rgb``, ``rgba`` or ``palette``."""
        return _COLOR_TYPES[self.color_type][0]

    @property
    def pixels(self) -> int:
        return self.width * self.height

    def raw_bytes(self) -> int:
        """Bytes the inflated IDAT stream must hold: filtered rows, one filter byte each."""
        bits = _COLOR_TYPES[self.color_type][1] * self.bit_depth
        if not self.interlaced:
            return self.height * (1 + (self.width * bits + 7) // 8)
        total = 0
        for x0, y0, dx, dy in _ADAM7:
            w = (self.width - x0 + dx - 1) // dx if self.width > x0 else 0
            h = (self.height - y0 + dy - 1) // dy if self.height > y0 else 0
            if w and h:
                total += h * (1 + (w * bits + 7) // 8)
        return total


@dataclass
class PngImage:
    """A decoded PNG: ``color`` (C, h, w) float32 in [0, 1], C ∈ {1, 3}; ``alpha`` (1, h, w) or None."""

    color: np.ndarray
    alpha: np.ndarray | None
    header: PngHeader
    where: str

    @property
    def width(self) -> int:
        return self.header.width

    @property
    def height(self) -> int:
        return self.header.height


def _fail(where: str, what: str, expected: str = _EXPECTED_PNG) -> ImageError:
    return ImageError(f"{what}; {expected}", where=where)


def parse_header(data: bytes, where: str) -> PngHeader:
    """Parse and check the signature and IHDR (the first 33 bytes of a PNG)."""
    if len(data) < 8 or data[:8] != PNG_SIGNATURE:
        what = "empty file" if not data else "not a PNG file (bad signature)"
        raise _fail(where, what)
    if len(data) < 33:
        raise _fail(where, "truncated PNG header")
    length, ctype = struct.unpack(">I4s", data[8:16])
    if ctype != b"IHDR" or length != 13:
        raise _fail(where, f"first chunk is {ctype!r} of {length} bytes, not a 13-byte IHDR")
    body = data[16:29]
    (crc,) = struct.unpack(">I", data[29:33])
    if zlib.crc32(b"IHDR" + body) != crc:
        raise _fail(where, "corrupt PNG header (IHDR CRC mismatch)")
    width, height, depth, color_type, compression, filter_method, interlace = struct.unpack(">IIBBBBB", body)
    if not (1 <= width < 2**31 and 1 <= height < 2**31):
        raise _fail(where, f"invalid size {width}x{height} in IHDR")
    if color_type not in _COLOR_TYPES or depth not in _COLOR_TYPES[color_type][2]:
        raise _fail(where, f"invalid colour type {color_type} with bit depth {depth}")
    if compression != 0 or filter_method != 0 or interlace not in (0, 1):
        raise _fail(where, "unknown compression, filter or interlace method in IHDR")
    return PngHeader(width, height, depth, color_type, bool(interlace))


def read_png_header(path: str | os.PathLike) -> PngHeader:
    """Read only the header of the PNG at ``path`` (33 bytes)."""
    where = str(path)
    try:
        with open_regular(path, where) as fh:
            head = fh.read(33)
    except OSError as exc:
        raise _open_error(where, exc) from None
    return parse_header(head, where)


def check_size(
    header: PngHeader, where: str, max_pixels: int = DEFAULT_MAX_PIXELS, max_side: int | None = None
) -> None:
    """Refuse an image larger than ``max_pixels`` (or wider/taller than ``max_side``) before decoding."""
    if header.pixels > max_pixels:
        raise ImageError(
            f"image is {header.width}x{header.height} = {header.pixels} pixels, over the limit of {max_pixels} "
            f"(decompression-bomb guard); expected at most {max_pixels} pixels (raise max_pixels, or --max-pixels, "
            "if this is intended)",
            where=where,
        )
    if max_side is not None and max(header.width, header.height) > max_side:
        raise ImageError(
            f"image is {header.width}x{header.height}; expected width and height at most {max_side}", where=where
        )


def _check_chunks(data: bytes, header: PngHeader, where: str) -> None:
    """Walk every chunk: CRCs, IEND present, and the IDAT stream inflating to exactly raw_bytes().

    Inflation runs in bounded pieces that are counted and discarded, so a bomb costs no memory.
    """
    need = header.raw_bytes()
    pos = 33
    idat_total = 0
    inflater = zlib.decompressobj()
    produced = 0
    seen_plte = False
    ended = False
    # First count IDAT bytes: a stream that cannot expand to `need` is refused before inflating.
    while pos + 12 <= len(data):
        length, ctype = struct.unpack(">I4s", data[pos : pos + 8])
        end = pos + 12 + length
        if length > 2**31 - 1 or end > len(data):
            raise _fail(where, f"truncated file: chunk {ctype!r} at byte {pos} claims {length} bytes past the end")
        body = data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : end])
        if zlib.crc32(ctype + body) != crc:
            raise _fail(where, f"corrupt file: CRC mismatch in chunk {ctype.decode('latin-1')!r} at byte {pos}")
        if ctype == b"IDAT":
            idat_total += length
        elif ctype == b"PLTE":
            seen_plte = True
        elif ctype == b"IEND":
            ended = True
            break
        pos = end
    if not ended:
        raise _fail(where, "truncated file: no IEND chunk")
    if header.color_type == 3 and not seen_plte:
        raise _fail(where, "palette image without a PLTE chunk")
    if idat_total * DEFLATE_MAX_RATIO + 64 < need:
        raise _fail(
            where,
            f"IDAT holds {idat_total} compressed bytes, which cannot expand to the {need} bytes a "
            f"{header.width}x{header.height} image needs (corrupt or decompression bomb)",
        )
    stride = 0 if header.interlaced else header.raw_bytes() // header.height  # filter byte + one row

    def check_filters(out: bytes, start: int) -> None:
        # Each row of a non-interlaced image starts with its filter type, 0..4 (PNG spec, 9.2).
        if not stride or not out:
            return
        first = (-start) % stride
        types = np.frombuffer(out, dtype=np.uint8)[first::stride]
        if types.size and int(types.max()) > 4:
            row = (start + first) // stride + int(np.argmax(types > 4))
            raise _fail(where, f"row {row} has filter type {int(types.max())}; expected 0 to 4 (corrupt image data)")

    pos = 33
    piece = 1 << 20
    while True:
        length, ctype = struct.unpack(">I4s", data[pos : pos + 8])
        if ctype == b"IEND":
            break
        if ctype == b"IDAT":
            chunk = data[pos + 8 : pos + 8 + length]
            try:
                out = inflater.decompress(chunk, piece)
                check_filters(out, produced)
                produced += len(out)
                while inflater.unconsumed_tail and produced <= need:
                    out = inflater.decompress(inflater.unconsumed_tail, piece)
                    check_filters(out, produced)
                    produced += len(out)
            except zlib.error as exc:
                raise _fail(where, f"corrupt image data (zlib: {exc})") from None
            if produced > need:
                raise _fail(
                    where,
                    f"image data expands beyond the {need} bytes a {header.width}x{header.height} image needs "
                    "(corrupt or decompression bomb)",
                )
        pos += 12 + length
    if produced < need or not inflater.eof:
        raise _fail(where, f"truncated image data: {produced} of {need} bytes")


def _open_error(where: str, exc: OSError) -> ImageError:
    reason = exc.strerror or type(exc).__name__
    return ImageError(f"cannot read file ({reason}); {_EXPECTED_PNG}", where=where)


def decode_png(
    data: bytes, where: str, *, max_pixels: int = DEFAULT_MAX_PIXELS, max_side: int | None = None
) -> PngImage:
    """Check and decode PNG bytes (see the module docstring). ``where`` names the source in errors."""
    header = parse_header(data[:33], where)
    check_size(header, where, max_pixels, max_side)
    _check_chunks(data, header, where)
    try:
        if header.bit_depth == 16 or header.pixels > _pillow_pixel_limit():
            return _decode_pypng(data, header, where)
        return _decode_pillow(data, header, where)
    except ImageError:
        raise
    except (OSError, ValueError, SyntaxError, pypng.Error, zlib.error) as exc:
        raise _fail(
            where, f"cannot decode PNG ({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from None


def png_file_limit(header: PngHeader) -> int:
    """The most bytes a PNG of ``header`` can sensibly hold: twice its raw image data (deflate's worst
    expansion is far less) plus room for ICC profiles, EXIF and text chunks."""
    return 2 * header.raw_bytes() + _ANCILLARY_SLACK


def _read_bounded(path: str | os.PathLike, where: str, max_pixels: int, max_side: int | None) -> bytes:
    """The bytes of the PNG at ``path``, read only after its header passed the size limits and its file
    size is plausible for that header."""
    try:
        with open_regular(path, where) as fh:
            head = fh.read(33)
            header = parse_header(head, where)
            check_size(header, where, max_pixels, max_side)
            size = os.fstat(fh.fileno()).st_size
            if size > png_file_limit(header):
                raise _fail(where, f"file is {size} bytes, far more than a {header.width}x{header.height} PNG holds")
            return head + fh.read(size)  # never past the size checked, if the file grows meanwhile
    except IsADirectoryError:
        raise ImageError(f"is a folder; {_EXPECTED_PNG}", where=where) from None
    except OSError as exc:
        raise _open_error(where, exc) from None


def read_png(path: str | os.PathLike, *, max_pixels: int = DEFAULT_MAX_PIXELS, max_side: int | None = None) -> PngImage:
    """Read the PNG at ``path`` as float32 channels-first values; refuse bombs before decoding."""
    where = str(path)
    data = _read_bounded(path, where, max_pixels, max_side)
    return decode_png(data, where, max_pixels=max_pixels, max_side=max_side)


def _pillow_pixel_limit() -> float:
    # Pillow warns above MAX_IMAGE_PIXELS and refuses above twice that; larger images (already
    # admitted by our own limit) go through pypng, which has no such global switch.
    limit = Image.MAX_IMAGE_PIXELS
    return float("inf") if limit is None else limit


def _decode_pillow(data: bytes, header: PngHeader, where: str) -> PngImage:
    with Image.open(io.BytesIO(data), formats=["PNG"]) as im:
        has_trns = "transparency" in im.info
        ct = header.color_type
        if ct == 0:
            mode = "LA" if has_trns else "L"
        elif ct == 4:
            mode = "LA"
        elif ct == 6 or has_trns:
            mode = "RGBA"
        else:
            mode = "RGB"
        im.load()
        converted = im.convert(mode) if im.mode != mode else im
        codes = np.asarray(converted).reshape(header.height, header.width, len(mode))  # (h, w, planes) uint8
        del converted
    # One float32 plane at a time into a channels-first array: the peak is the codes plus the result
    # (decode_bytes), not three float copies. float32 division by 255 as before (bit-identical values).
    planes = np.empty((len(mode), header.height, header.width), dtype=np.float32)
    for c in range(len(mode)):
        np.divide(codes[:, :, c], np.float32(255.0), out=planes[c], dtype=np.float32)
    del codes
    return PngImage(*_split_planes(planes), header=header, where=where)


def _decode_pypng(data: bytes, header: PngHeader, where: str) -> PngImage:
    # asDirect expands palettes and tRNS into RGB(A)/alpha and honours sBIT (the reported bitdepth
    # is then the significant bits), so the maximum code is 2**bitdepth - 1.
    width, height, rows, info = pypng.Reader(bytes=data).asDirect()
    n = info["planes"]
    maxval = np.float32(2 ** info["bitdepth"] - 1)
    dtype = np.uint16 if info["bitdepth"] > 8 else np.uint8
    planes = np.empty((n, height, width), dtype=np.float32)
    for i, row in enumerate(rows):  # rows are decoded lazily: one row of codes at a time
        planes[:, i, :] = np.asarray(row, dtype=dtype).reshape(width, n).T
    planes /= maxval
    return PngImage(*_split_planes(planes), header=header, where=where)


def _split_planes(planes: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(planes, h, w) -> color (C, h, w), alpha (1, h, w) | None, as views (no copy)."""
    if planes.shape[0] in (2, 4):
        return planes[:-1], planes[-1:]
    return planes, None


def decode_bytes(header: PngHeader) -> tuple[int, int]:
    """``(kept, transient)`` bytes of decoding a PNG of ``header``: the float32 planes it yields, and the
    codes that live beside them while decoding (Pillow's image holds up to 4 bytes a pixel, then the
    (h, w, planes) uint8 array; pypng's 16-bit rows come one at a time)."""
    planes = _COLOR_TYPES[header.color_type][1]
    if header.color_type in (0, 2, 3):
        planes += 1  # tRNS or a palette may add an alpha plane
    kept = header.pixels * min(planes, 4) * 4
    pillow = not (header.bit_depth == 16 or header.pixels > _pillow_pixel_limit())
    return kept, (header.pixels * 8 if pillow else 0)


def verify_png(
    path: str | os.PathLike, *, max_pixels: int = DEFAULT_MAX_PIXELS, max_side: int | None = None
) -> PngHeader:
    """Check a PNG completely *without decoding its pixels*: header, size limits, every chunk's CRC, the
    IDAT stream inflating (in bounded pieces) to exactly the bytes the header needs, and every row's
    filter type. Memory: the file's bytes and 1 MiB pieces; what ``lasagna validate`` runs."""
    where = str(path)
    data = _read_bounded(path, where, max_pixels, max_side)
    header = parse_header(data[:33], where)
    _check_chunks(data, header, where)
    return header


# --- writing ---------------------------------------------------------------------------------------


def _as_numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):  # a torch tensor, without importing torch here
        x = x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def quantize(values, bit_depth: BitDepth, where: str, *, clip: bool = False) -> np.ndarray:
    """Round values in [0, 1] to unsigned integer codes; out-of-range or NaN values are an error."""
    v = _as_numpy(values)
    if not np.isfinite(v).all():
        raise ImageError(
            f"{int((~np.isfinite(v)).sum())} values are NaN or infinite; expected finite values in [0, 1]", where=where
        )
    if clip:
        v = np.clip(v, 0.0, 1.0)
    elif v.size and (v.min() < 0.0 or v.max() > 1.0):
        raise ImageError(
            f"values span [{v.min():.6g}, {v.max():.6g}]; expected values in [0, 1] (pass clip=True to clamp)",
            where=where,
        )
    maxval = 2**bit_depth - 1
    return np.rint(v * maxval).astype(np.uint16 if bit_depth == 16 else np.uint8)


def encode_png(color, alpha=None, *, bit_depth: BitDepth = 8, clip: bool = False, where: str = "png") -> bytes:
    """Encode ``color`` (C, h, w), C ∈ {1, 3}, and optional ``alpha`` (1, h, w) as PNG bytes."""
    if bit_depth not in (8, 16):
        raise ImageError(f"bit depth {bit_depth!r}; expected 8 or 16", where=where)
    c = _as_numpy(color)
    if c.ndim == 2:
        c = c[None]
    if c.ndim != 3 or c.shape[0] not in (1, 3) or c.shape[1] < 1 or c.shape[2] < 1:
        raise ImageError(f"colour has shape {tuple(c.shape)}; expected (1 or 3, h, w)", where=where)
    planes = [c]
    if alpha is not None:
        a = _as_numpy(alpha)
        if a.ndim == 2:
            a = a[None]
        if a.shape != (1,) + c.shape[1:]:
            raise ImageError(f"alpha has shape {tuple(a.shape)}; expected {(1,) + c.shape[1:]}", where=where)
        planes.append(a)
    q = quantize(np.concatenate(planes, axis=0), bit_depth, where, clip=clip)  # (P, h, w)
    n, h, w = q.shape
    hwc = np.ascontiguousarray(q.transpose(1, 2, 0))
    buf = io.BytesIO()
    if bit_depth == 8:
        # fromarray infers L / LA / RGB / RGBA from the uint8 array's shape.
        Image.fromarray(hwc[:, :, 0] if n == 1 else hwc).save(buf, format="PNG")
    else:
        # Pillow cannot write 16-bit RGB(A) or gray+alpha; pypng writes every 16-bit kind.
        writer = pypng.Writer(w, h, greyscale=n in (1, 2), alpha=n in (2, 4), bitdepth=16, compression=6)
        writer.write_array(buf, hwc.reshape(-1))
    return buf.getvalue()


def encode_codes(hwc: np.ndarray, where: str = "png") -> bytes:
    """Encode 8-bit codes (h, w, C) uint8, C ∈ {1, 2, 3, 4} (gray, gray + alpha, RGB, RGBA), as PNG bytes: what
    ``encode_png`` writes for their values / 255, without the float64 copies (4 bytes a code → 8 each, twice)."""
    if hwc.dtype != np.uint8 or hwc.ndim != 3 or hwc.shape[2] not in (1, 2, 3, 4):
        raise ImageError(f"codes are {hwc.dtype} of shape {tuple(hwc.shape)}; expected uint8 (h, w, 1 to 4)", where)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(hwc[:, :, 0] if hwc.shape[2] == 1 else hwc)).save(buf, format="PNG")
    return buf.getvalue()


def _chunk(ctype: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + ctype + body + struct.pack(">I", zlib.crc32(ctype + body))


def _filter_rows(rows: np.ndarray, above: np.ndarray) -> np.ndarray:
    """PNG-filter a band of raw rows (n, stride) uint8, ``above`` the row before it (zeros at the top): every row
    takes the Up filter (PNG spec 9.2, type 2: each byte minus the byte above; the first row of an image, above
    zeros, is stored as it is). Returns (n, 1 + stride) with the filter byte first.

    Why Up and not libpng's per-row heuristic (the least sum of absolute values over the five filters): on this
    project's outputs — photographs, composites, smooth multipliers and normal maps, 8- and 16-bit — Up compressed
    as well or better (a 12 MP photo: 4.6 MB against the heuristic's 5.4 MB at zlib level 6) at a tenth of the
    filtering time (0.2 s against 1.8 s for Paeth alone in numpy), which is what the band encoder spent most on."""
    n, stride = rows.shape
    out = np.empty((n, 1 + stride), dtype=np.uint8)
    out[:, 0] = 2
    np.subtract(rows[:1], above[None], out=out[:1, 1:])  # uint8 arithmetic wraps modulo 256, as the filter is
    np.subtract(rows[1:], rows[:-1], out=out[1:, 1:])
    return out


# The sRGB chunk's rendering intent (PNG spec 11.3.3.5): 0, perceptual, as tagged inputs are converted.
SRGB_INTENT = 0

# PNG colour type (PNG spec, 11.2.2) of samples per pixel: gray, gray + alpha, RGB, RGBA.
_COLOR_TYPE_OF = {1: 0, 2: 4, 3: 2, 4: 6}


def quantize_band(values: np.ndarray, bit_depth: BitDepth) -> np.ndarray:
    """Codes of a band of values (float, already checked finite): clamped to [0, 1], then 2^d − 1 times the value
    rounded half to even (``quantize`` with ``clip``, without its checks and copies of the whole image)."""
    v = np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0)
    v *= 2**bit_depth - 1
    return np.rint(v, out=v).astype(np.uint16 if bit_depth == 16 else np.uint8)


def encode_bands(bands, width: int, height: int, *, bit_depth: BitDepth = 8, srgb: bool = False) -> bytes:
    """A PNG from ``bands``, an iterable of (rows, width, C) code arrays from the top (C = 1 gray, 2 gray + alpha,
    3 RGB, 4 RGBA; uint8 for ``bit_depth`` 8, uint16 for 16), encoded as they come: the memory is the compressed
    output and one band, never a copy of the whole image (what composites, layer PNGs and the rasters of ORA
    files use for canvases of any size). ``srgb``: an ``sRGB`` chunk (``SRGB_INTENT``) says the colours are sRGB,
    as every composite's are (tagged inputs are converted on reading, ``lasagna.io.image``)."""
    if bit_depth not in (8, 16):
        raise ImageError(f"bit depth {bit_depth!r}; expected 8 or 16", where="png")
    deflate = zlib.compressobj(6)
    parts = [PNG_SIGNATURE]
    above = None
    rows_seen = 0
    pending: list[bytes] = []
    channels = 0
    for band in bands:
        band = np.asarray(band)
        if band.ndim != 3 or band.shape[1] != width or band.shape[2] not in _COLOR_TYPE_OF:
            raise ImageError(f"band has shape {band.shape}; expected (rows, {width}, 1 to 4)", where="png")
        if above is None:
            channels = band.shape[2]
            header = struct.pack(">IIBBBBB", width, height, bit_depth, _COLOR_TYPE_OF[channels], 0, 0, 0)
            parts.append(_chunk(b"IHDR", header))
            if srgb:
                parts.append(_chunk(b"sRGB", bytes([SRGB_INTENT])))
            above = np.zeros(width * channels * bit_depth // 8, dtype=np.uint8)
        elif band.shape[2] != channels:
            raise ImageError(f"band has {band.shape[2]} channels; expected {channels} as the first", where="png")
        codes = band.astype(">u2" if bit_depth == 16 else np.uint8, copy=False)  # PNG samples are big-endian
        raw = np.ascontiguousarray(codes).view(np.uint8).reshape(band.shape[0], -1)
        pending.append(deflate.compress(_filter_rows(raw, above).tobytes()))
        above = raw[-1].copy()
        rows_seen += raw.shape[0]
        if sum(map(len, pending)) >= 1 << 20:  # IDAT chunks of about 1 MiB
            parts.append(_chunk(b"IDAT", b"".join(pending)))
            pending = []
    if rows_seen != height or above is None:
        raise ImageError(f"got {rows_seen} rows; expected {height}", where="png")
    pending.append(deflate.flush())
    parts.append(_chunk(b"IDAT", b"".join(pending)))
    parts.append(_chunk(b"IEND", b""))
    return b"".join(parts)


def encode_rgb8_bands(bands, width: int, height: int) -> bytes:
    """An 8-bit RGB PNG tagged sRGB from (rows, width, 3) uint8 ``bands`` (``encode_bands``)."""
    return encode_bands(bands, width, height, bit_depth=8, srgb=True)


def write_png(path: str | os.PathLike, color, alpha=None, *, bit_depth: BitDepth = 8, clip: bool = False) -> None:
    """Write a PNG atomically (temporary file beside ``path``, then rename). See :func:`encode_png`."""
    data = encode_png(color, alpha, bit_depth=bit_depth, clip=clip, where=str(path))
    write_output(path, data, ImageError)
