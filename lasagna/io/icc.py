"""ICC profiles of input images: every tagged input is converted to sRGB, the working space, when it is read.

- 8-bit images (JPEG, WebP, TIFF, and PNG with an ``iCCP`` chunk, ``png_icc_profile``) go through LittleCMS in
  ``PIL.ImageCms`` (``pil_to_srgb``), intent ``ICC_INTENT``.
- 16-bit and float images cannot: Pillow's ImageCms transforms 8-bit modes only (it has no 16-bit RGB image mode;
  ``buildTransform`` refuses ``RGB;16``, ``RGBA;16B`` and ``I;16``), and no LittleCMS binding for numpy ships with
  Lasagna's dependencies. So a 16-bit RGB image tagged with a *matrix-shaper* profile — Display P3, Adobe RGB,
  ProPhoto, Rec. 2020, what cameras and phones embed — is converted here in float64 (``matrix_shaper_to_srgb``):
  the profile's tone curves (``rTRC``/``gTRC``/``bTRC``: ``curv`` or ``para``, ICC.1:2010 sections 10.6 and 10.18)
  to linear light, its colorants (``rXYZ``/``gXYZ``/``bXYZ``, D50) to the PCS, the inverse of sRGB's D50 colorants
  to linear sRGB, clipped to [0, 1] and encoded by IEC 61966-2-1. That is the transform LittleCMS builds between
  two matrix-shaper profiles for every intent (neither has perceptual tables), so the 16-bit result agrees with
  Pillow's 8-bit one to within the 8-bit rounding (tested). A 16-bit image with another kind of profile (a table
  profile, gray, CMYK) is read as sRGB codes with one warning.

Outputs hold sRGB values, and the source profile is embedded in none (the pixels are no longer in it):
``composite.png`` and an ORA's ``mergedimage.png`` carry an ``sRGB`` chunk (``lasagna.io.png.encode_bands``); layer
PNGs are untagged (a multiplier, a range-mapped or a normal-map layer is not a colour), which readers take as sRGB;
a PSD has no ICC resource (Photoshop assigns its working space, sRGB by default) — tested in tests/io/test_icc.py.
"""

from __future__ import annotations

import io
import struct
import warnings
import zlib
from pathlib import Path

import numpy as np

from lasagna.atomic import open_regular

# The rendering intent of a tagged image's conversion to sRGB: perceptual, what viewers and Photoshop's "convert to
# profile" use, so colours outside sRGB are compressed, not clipped where a profile has a table for it.
ICC_INTENT = "perceptual"

# The bytes of an iCCP chunk's compressed profile that are inflated at most: ICC profiles of photographs are a
# few kB (Display P3: 536 bytes); 4 MiB holds any real profile (a CMYK table profile is ~0.5–3 MB) and bounds a
# zip bomb hidden in the chunk.
MAX_ICC_BYTES = 4 << 20


def _warn(where: str, what: str) -> None:
    warnings.warn(f"{where}: {what}; read as sRGB", stacklevel=3)


def png_icc_profile(path: str | Path, where: str) -> bytes | None:
    """The ICC profile of a PNG's ``iCCP`` chunk (PNG spec 11.3.3.3: name, 0, method 0, zlib data), or None; the
    chunks before the first IDAT are read, nothing is decoded."""
    with open_regular(Path(path), where) as fh:
        fh.seek(8)
        while True:
            head = fh.read(8)
            if len(head) < 8:
                return None
            length, ctype = struct.unpack(">I4s", head)
            if ctype in (b"IDAT", b"IEND"):
                return None
            if ctype != b"iCCP":
                fh.seek(length + 4, io.SEEK_CUR)
                continue
            body = fh.read(length)
            name_end = body.find(b"\0")
            if name_end < 0 or name_end + 2 > len(body) or body[name_end + 1] != 0:
                _warn(where, "its iCCP chunk is malformed")
                return None
            inflater = zlib.decompressobj()
            try:
                data = inflater.decompress(body[name_end + 2 :], MAX_ICC_BYTES)
            except zlib.error:
                _warn(where, "its iCCP chunk does not inflate")
                return None
            if inflater.unconsumed_tail:
                _warn(where, f"its ICC profile is larger than {MAX_ICC_BYTES} bytes")
                return None
            return data


def profile_name(icc: bytes) -> str:
    """The profile's description (``ImageCms.getProfileDescription``), one line, or "unnamed"."""
    from PIL import ImageCms

    try:
        profile = ImageCms.ImageCmsProfile(io.BytesIO(icc))
        return " ".join(ImageCms.getProfileDescription(profile).split()) or "unnamed"
    except (ImageCms.PyCMSError, OSError, ValueError):
        return "unnamed"


def pil_to_srgb(im, icc: bytes, where: str):
    """A Pillow image tagged with ``icc`` converted to sRGB by LittleCMS (alpha kept), or the image unchanged with
    one warning when the profile cannot be read or converted for its mode."""
    from PIL import ImageCms

    try:
        src = ImageCms.ImageCmsProfile(io.BytesIO(icc))
    except (ImageCms.PyCMSError, OSError, ValueError) as exc:
        _warn(where, f"cannot read its ICC profile ({' '.join(str(exc).split())[:80]})")
        return im
    name = profile_name(icc)
    if im.mode == "P":
        im = im.convert("RGBA" if "transparency" in im.info else "RGB")
    if im.mode not in ("RGB", "RGBA", "L", "CMYK"):
        _warn(where, f"cannot convert its ICC profile {name!r} for a {im.mode} image")
        return im
    try:
        out = ImageCms.profileToProfile(
            im,
            src,
            ImageCms.createProfile("sRGB"),
            renderingIntent=ImageCms.Intent[ICC_INTENT.upper()],
            outputMode="RGBA" if im.mode == "RGBA" else "RGB",
        )
    except (ImageCms.PyCMSError, OSError, ValueError) as exc:
        _warn(where, f"cannot convert its ICC profile {name!r} to sRGB ({' '.join(str(exc).split())[:80]})")
        return im
    out.info.pop("icc_profile", None)
    return out


def codes_to_srgb(color: np.ndarray, icc: bytes, where: str) -> np.ndarray:
    """8-bit values (C, h, w) float32 (codes/255) of an image tagged ``icc`` → sRGB values (3, h, w)
    (``pil_to_srgb``)."""
    from PIL import Image

    codes = np.round(np.moveaxis(color, 0, -1) * 255.0).astype(np.uint8)
    im = Image.fromarray(codes[..., 0] if codes.shape[-1] == 1 else codes, "L" if codes.shape[-1] == 1 else "RGB")
    out = pil_to_srgb(im, icc, where)
    if out is im:
        return color
    values = np.asarray(out.convert("RGB"), dtype=np.float32) / np.float32(255.0)
    return np.ascontiguousarray(np.moveaxis(values, -1, 0))


# -- matrix-shaper profiles in float64 (module docstring) ------------------------------------------------------------


def _tags(icc: bytes) -> dict[bytes, bytes]:
    """Tag signature → its data (ICC.1:2010 section 7.3: a count at byte 128, then (signature, offset, size))."""
    (count,) = struct.unpack_from(">I", icc, 128)
    tags = {}
    for i in range(count):
        sig, off, size = struct.unpack_from(">4sII", icc, 132 + 12 * i)
        tags[sig] = icc[off : off + size]
    return tags


def _s15f16(data: bytes, offset: int, n: int) -> list[float]:
    return [v / 65536.0 for v in struct.unpack_from(f">{n}i", data, offset)]


def _xyz(data: bytes) -> np.ndarray:
    if data[:4] != b"XYZ ":
        raise ValueError(f"colorant of type {data[:4]!r}; expected 'XYZ '")
    return np.array(_s15f16(data, 8, 3))


def _tone_curve(data: bytes, v: np.ndarray) -> np.ndarray:
    """The curve of a ``curv`` or ``para`` tag applied to v in [0, 1] (float64): device value → linear."""
    kind = data[:4]
    if kind == b"curv":
        (n,) = struct.unpack_from(">I", data, 8)
        if n == 0:
            return v
        if n == 1:
            return v ** (struct.unpack_from(">H", data, 12)[0] / 256.0)
        table = np.array(struct.unpack_from(f">{n}H", data, 12), dtype=np.float64) / 65535.0
        return np.interp(v, np.linspace(0.0, 1.0, n), table)
    if kind == b"para":
        (fn,) = struct.unpack_from(">H", data, 8)
        count = {0: 1, 1: 3, 2: 4, 3: 5, 4: 7}.get(fn)
        if count is None:
            raise ValueError(f"parametric curve of function type {fn}; expected 0–4")
        g, a, b, c, d, e, f = (_s15f16(data, 12, count) + [0.0] * 7)[:7]
        if fn == 0:
            return v**g
        if fn in (1, 2):
            x = np.maximum(a * v + b, 0.0)
            return np.where(v >= -b / a, x**g, 0.0) + (c if fn == 2 else 0.0)
        return np.where(v >= d, np.maximum(a * v + b, 0.0) ** g + e, c * v + f)
    raise ValueError(f"tone curve of type {kind!r}; expected 'curv' or 'para'")


def matrix_shaper_to_srgb(color: np.ndarray, icc: bytes) -> np.ndarray:
    """(3, h, w) values in [0, 1] of an RGB image tagged with matrix-shaper profile ``icc`` → sRGB values (3, h, w)
    float32 (module docstring). ``ValueError`` for a profile that is not an RGB matrix-shaper."""
    from PIL import ImageCms

    if icc[16:20] != b"RGB ":
        raise ValueError(f"a {icc[16:20].decode('latin-1').strip()!r} profile; expected an RGB one")
    tags = _tags(icc)
    missing = [t.decode() for t in (b"rXYZ", b"gXYZ", b"bXYZ", b"rTRC", b"gTRC", b"bTRC") if t not in tags]
    if missing:
        raise ValueError(f"no {', '.join(missing)} tag (not a matrix-shaper profile)")
    src = np.stack([_xyz(tags[t]) for t in (b"rXYZ", b"gXYZ", b"bXYZ")], axis=1)  # columns: colorants (D50)
    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).profile
    dst = np.array([srgb.red_colorant[0], srgb.green_colorant[0], srgb.blue_colorant[0]], dtype=np.float64).T
    m = np.linalg.solve(dst, src)  # linear source RGB → linear sRGB
    curves = (b"rTRC", b"gTRC", b"bTRC")
    linear = np.stack([_tone_curve(tags[t], color[i].astype(np.float64)) for i, t in enumerate(curves)])
    out = np.einsum("ij,jhw->ihw", m, linear).clip(0.0, 1.0)
    # The one sRGB encoding (lasagna.compose.color), imported here: reading an image's header and refusing it
    # needs no torch (a refused edit then costs no torch import, ~1.5 s).
    import torch

    from lasagna.compose.color import linear_to_srgb

    return linear_to_srgb(torch.from_numpy(out)).numpy().astype(np.float32)


def wide_to_srgb(color: np.ndarray, icc: bytes, where: str) -> np.ndarray:
    """16-bit or float values (C, h, w) of an image tagged ``icc`` → sRGB (``matrix_shaper_to_srgb``), or unchanged
    with one warning (gray, CMYK or a table profile)."""
    if color.shape[0] != 3:
        _warn(where, f"cannot convert its ICC profile {profile_name(icc)!r} for a 16-bit gray image")
        return color
    try:
        return matrix_shaper_to_srgb(color, icc)
    except (ValueError, struct.error) as exc:
        _warn(where, f"cannot convert its ICC profile {profile_name(icc)!r} at 16 bits ({exc})")
        return color


__all__ = [
    "ICC_INTENT",
    "MAX_ICC_BYTES",
    "codes_to_srgb",
    "matrix_shaper_to_srgb",
    "pil_to_srgb",
    "png_icc_profile",
    "profile_name",
    "wide_to_srgb",
]
