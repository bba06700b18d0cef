"""An independent OpenRaster flattener (numpy float64, W3C formulas), standing in for a paint program.

Reads stack.xml with ElementTree and layer PNGs with pypng; no ``lasagna`` import. The bottom layer
must be opaque (our exports add an opaque background), so every blend is the opaque-backdrop form
Co = Cb + α(B(Cb, Cs) − Cb), clamped to [0, 1] after each layer like 8/16-bit paint programs;
``quantize=True`` also rounds to 8 bits after each layer, as Krita's 8-bit images do.
"""

from __future__ import annotations

import io
import zipfile
from xml.etree import ElementTree as ET

import numpy as np
import png


def _dodge(cb, cs):
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.where(cs >= 1.0, 1.0, np.minimum(1.0, cb / (1.0 - cs)))
    return np.where(cb <= 0.0, 0.0, out)


BLEND = {
    "svg:src-over": lambda cb, cs: cs,
    "svg:multiply": lambda cb, cs: cb * cs,
    "svg:screen": lambda cb, cs: cb + cs - cb * cs,
    "svg:plus": lambda cb, cs: cb + cs,
    "svg:color-dodge": _dodge,
}


def _rgba(data: bytes) -> np.ndarray:
    w, h, rows, info = png.Reader(bytes=data).asRGBA()
    return np.array([list(r) for r in rows], dtype=np.float64).reshape(h, w, 4) / (2 ** info["bitdepth"] - 1)


def flatten(path, *, quantize: bool = False) -> np.ndarray:
    """(H, W, 3) float64 in [0, 1]."""
    with zipfile.ZipFile(path) as zf:
        root = ET.fromstring(zf.read("stack.xml"))
        W, H = int(root.get("w")), int(root.get("h"))
        layers = list(root.find("stack"))[::-1]  # bottom first
        out = None
        for el in layers:
            if el.get("visibility", "visible") == "hidden":
                continue
            rgba = _rgba(zf.read(el.get("src")))
            x, y = int(el.get("x", 0)), int(el.get("y", 0))
            h, w = rgba.shape[:2]
            if out is None:
                assert (x, y, w, h) == (0, 0, W, H) and (rgba[:, :, 3] == 1).all(), "bottom layer must be opaque"
                out = rgba[:, :, :3].copy()
                continue
            x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + w, W), min(y + h, H)
            if x0 >= x1 or y0 >= y1:
                continue
            src = rgba[y0 - y : y1 - y, x0 - x : x1 - x]
            cb = out[y0:y1, x0:x1]
            a = src[:, :, 3:] * float(el.get("opacity", 1.0))
            res = np.clip(cb + a * (BLEND[el.get("composite-op", "svg:src-over")](cb, src[:, :, :3]) - cb), 0, 1)
            if quantize:
                res = np.rint(res * 255) / 255
            out[y0:y1, x0:x1] = res
    return out


def read_png_rgb(data: bytes) -> np.ndarray:
    """(H, W, 3) float64 of a PNG's colour (mergedimage, thumbnail)."""
    return _rgba(data)[:, :, :3]


def png_size(data: bytes) -> tuple[int, int]:
    r = png.Reader(file=io.BytesIO(data))
    r.preamble()
    return r.width, r.height
